"""Reading, building and writing robot missions."""
