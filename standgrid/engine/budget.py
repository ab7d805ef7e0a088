"""The memory budget every engine stays within (spilling to disk or cutting smaller chunks)."""

from __future__ import annotations

from dataclasses import dataclass

from standgrid.errors import StandgridError

#: Default budget of one stage in one process (2 GiB).
DEFAULT_MEMORY_BUDGET = 2 << 30


class BudgetError(StandgridError, ValueError):
    """A memory budget that cannot work."""


@dataclass(frozen=True)
class MemoryBudget:
    """Bytes one process (one dask worker) may hold for a stage's data."""

    bytes: int = DEFAULT_MEMORY_BUDGET

    def __post_init__(self) -> None:
        if self.bytes < 16 << 20:
            raise BudgetError(f"memory budget {self.bytes} B is below the 16 MB minimum")

    @classmethod
    def megabytes(cls, mb: float) -> MemoryBudget:
        return cls(int(mb * 2**20))

    def points(self, bytes_per_point: int) -> int:
        """How many points of ``bytes_per_point`` (all copies a step makes) fit."""
        return max(1, self.bytes // max(1, bytes_per_point))
