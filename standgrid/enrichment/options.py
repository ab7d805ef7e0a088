"""The parameters of enrichment (documented in docs/METRICS.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from standgrid.enrichment.stands import CoverageRule
from standgrid.errors import OptionError

#: field -> (least value, greatest value, least excluded): every number's range.
_RANGES: dict[str, tuple[float, float, bool]] = {
    "pixel_size": (0.0, math.inf, True),
    "halo": (0.0, math.inf, False),
    "height_break": (0.0, math.inf, False),
    "cloth_resolution": (0.0, math.inf, True),
    "rigidness": (1, 3, False),
    "tree_pixel_size": (0.0, math.inf, True),
    "tree_min_height": (0.0, math.inf, False),
    "min_observed_fraction": (0.0, 1.0, False),
    "min_density_pts_m2": (0.0, math.inf, False),
    "coverage_closing_m": (0.0, math.inf, False),
}


def check_range(name: str, value: object, low: float, high: float, open_low: bool) -> None:
    """Refuse (:class:`~standgrid.errors.OptionError`) a value outside ``[low, high]`` (or
    ``(low, high]``), or no finite number."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        number = float(value)
        if math.isfinite(number) and low <= number <= high and not (open_low and number == low):
            return
    bound = f"> {low:g}" if open_low else f">= {low:g}"
    bound += "" if math.isinf(high) else f" and <= {high:g}"
    raise OptionError(name, f"{value!r}: give a number {bound}")


@dataclass(frozen=True)
class EnrichOptions:
    """Parameters of enrichment (documented in docs/METRICS.md); validated when made
    (:class:`~standgrid.errors.OptionError` naming the field at fault)."""

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
    #: the epochs to enrich (default: all)
    epochs: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for name, (low, high, open_low) in _RANGES.items():
            check_range(name, getattr(self, name), low, high, open_low)
        if isinstance(self.epochs, str) or not all(isinstance(e, str) for e in self.epochs):
            raise OptionError("epochs", f"{self.epochs!r}: give a tuple of epoch labels")

    @property
    def coverage_rule(self) -> CoverageRule:
        """The least a stand must have observed for its metrics to be reported."""
        return CoverageRule(self.min_observed_fraction, self.min_density_pts_m2)
