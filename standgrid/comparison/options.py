"""The parameters of a comparison between two epochs."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from standgrid.enrichment.options import check_range
from standgrid.enrichment.stands import CoverageRule
from standgrid.errors import OptionError


@dataclass(frozen=True)
class CompareOptions:
    """Which epochs to compare and how (docs/METRICS.md, "Change"); validated when made
    (:class:`~standgrid.errors.OptionError` naming the field at fault).

    ``epoch_from`` / ``epoch_to`` default to the first and the last epoch; with
    ``other_catalog``, ``epoch_to`` is read from that catalog (on the same grid).
    """

    epoch_from: str | None = None
    epoch_to: str | None = None
    other_catalog: str | Path | None = None
    #: trees of the two epochs further apart than this (m) are never matched
    max_distance: float = 2.0
    #: least share of a stand observed by both epochs for its change to be reported
    min_observed_fraction: float = CoverageRule.min_observed_fraction

    def __post_init__(self) -> None:
        check_range("max_distance", self.max_distance, 0.0, math.inf, True)
        check_range("min_observed_fraction", self.min_observed_fraction, 0.0, 1.0, False)
        for name in ("epoch_from", "epoch_to"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, str):
                raise OptionError(name, f"{value!r}: give an epoch label")
