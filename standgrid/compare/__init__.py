"""Change between campaigns."""
