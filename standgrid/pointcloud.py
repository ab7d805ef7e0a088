"""The in-memory point cloud every stage passes along: float64 xyz plus named per-point fields."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from standgrid.geometry import Matrix4, transform_points


@dataclass(frozen=True, eq=False)
class PointCloud:
    """Points ``xyz`` (N, 3) float64 and per-point ``fields`` (each of length N).

    Field names follow the source file (``intensity``, ``normal_x``, ...). Coordinates are
    always float64; fields keep their own dtype.
    """

    xyz: NDArray[np.float64]
    fields: Mapping[str, NDArray[np.generic]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        xyz = np.ascontiguousarray(self.xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"xyz must have shape (N, 3), got {xyz.shape}")
        fields = {name: np.asarray(values) for name, values in self.fields.items()}
        for name, values in fields.items():
            if values.shape[:1] != (len(xyz),):
                raise ValueError(
                    f"field {name!r} has {values.shape[:1]} values for {len(xyz)} points"
                )
        object.__setattr__(self, "xyz", xyz)
        object.__setattr__(self, "fields", fields)

    @classmethod
    def empty(cls, fields: Mapping[str, np.dtype] | None = None) -> PointCloud:
        return cls(np.empty((0, 3)), {k: np.empty(0, dtype=dt) for k, dt in (fields or {}).items()})

    def __len__(self) -> int:
        return len(self.xyz)

    def transformed(self, pose: Matrix4) -> PointCloud:
        """The same points mapped by a 4x4 pose (fields shared, not copied)."""
        return PointCloud(transform_points(pose, self.xyz), self.fields)

    def select(self, index: ArrayLike) -> PointCloud:
        """A subset by boolean mask or integer index."""
        idx = np.asarray(index)
        return PointCloud(self.xyz[idx], {k: v[idx] for k, v in self.fields.items()})

    def with_fields(self, **fields: ArrayLike) -> PointCloud:
        """A copy with fields added or replaced."""
        merged: dict[str, NDArray[np.generic]] = dict(self.fields)
        merged.update({k: np.asarray(v) for k, v in fields.items()})
        return PointCloud(self.xyz, merged)

    @staticmethod
    def concat(clouds: Iterable[PointCloud]) -> PointCloud:
        """Stack clouds that carry the same field names (``ValueError`` otherwise)."""
        parts = list(clouds)
        if not parts:
            return PointCloud.empty()
        names = list(parts[0].fields)
        for c in parts[1:]:
            if set(c.fields) != set(names):
                raise ValueError(
                    f"cannot concatenate clouds with fields {sorted(names)} and {sorted(c.fields)}"
                )
        return PointCloud(
            np.concatenate([c.xyz for c in parts]),
            {n: np.concatenate([c.fields[n] for c in parts]) for n in names},
        )
