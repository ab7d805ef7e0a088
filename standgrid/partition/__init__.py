"""Partitioning the map: the fixed stand grid, Voronoi cells, and the streaming partition engine."""
