"""The parameters of enrichment (documented in docs/METRICS.md)."""

from __future__ import annotations

from dataclasses import dataclass, field

from standgrid.engine.budget import MemoryBudget
from standgrid.enrich.stands import CoverageRule


@dataclass(frozen=True)
class EnrichOptions:
    """Parameters of enrichment (documented in docs/METRICS.md)."""

    pixel_size: float = 1.0
    halo: float = 10.0
    height_break: float = 2.0
    cloth_resolution: float = 0.5
    rigidness: int = 1
    tree_pixel_size: float = 0.5
    tree_min_height: float = 2.0
    min_observed_fraction: float = 0.25
    min_density_pts_m2: float = 2.0
    coverage_closing_m: float = 2.0
    epochs: tuple[str, ...] = ()
    #: what one process (each dask worker) may hold for a chunk; sizes the chunks
    memory_budget: MemoryBudget = field(default_factory=MemoryBudget)

    @property
    def coverage_rule(self) -> CoverageRule:
        """The least a stand must have observed for its metrics to be reported."""
        return CoverageRule(self.min_observed_fraction, self.min_density_pts_m2)
