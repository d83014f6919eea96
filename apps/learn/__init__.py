"""`archery learn`: start, resume or follow one learning session on running services."""
