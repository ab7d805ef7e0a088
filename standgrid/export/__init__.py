"""Exporting: LAS/LAZ tiles, the GeoPackage index, the catalog folder."""
