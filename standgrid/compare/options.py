"""The parameters of a comparison between two epochs."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from standgrid.enrich.stands import CoverageRule


@dataclass(frozen=True)
class CompareOptions:
    """Which epochs to compare and how (docs/METRICS.md, "Change").

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
