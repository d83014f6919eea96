"""`archery up`: the launch description, the supervisor and its restart policy."""
