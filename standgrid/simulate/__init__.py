"""A deterministic forest-mission simulator with known ground truth."""
