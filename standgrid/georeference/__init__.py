"""Georeferencing: GNSS fixes -> a transform from the SLAM map frame into a projected CRS."""
