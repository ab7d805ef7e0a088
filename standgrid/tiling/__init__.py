"""Tiling: missions georeferenced and partitioned into a catalog's tiles."""
