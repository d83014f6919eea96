"""`archery dashboard`: a live view of a learning session in the browser."""
