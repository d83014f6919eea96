"""`archery film`: a video of one shot, re-simulated from a session's journal."""
