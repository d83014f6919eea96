"""Command-line tools around the learner: `archery learn` (one session), `archery experiment`
(algorithms compared offline), the session report and its plots."""
