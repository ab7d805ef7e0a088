"""Deprecated location: use :mod:`standgrid.catalog.invalidate` (kept one release)."""

from standgrid.catalog.invalidate import (  # noqa: F401
    ENRICH_POINT_FIELDS,
    clear_invalidation,
    invalidate_comparisons,
    invalidate_epochs,
    retile_reason,
    without_enrichment,
)
