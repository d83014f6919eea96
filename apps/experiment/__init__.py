"""`archery experiment`: the paper's simulation experiment on the ballistic world or a fleet of
robots, its figures and statistics."""
