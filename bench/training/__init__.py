"""Training: quality against time, the layered scene against format 1, training steps, long captures, Ray."""
