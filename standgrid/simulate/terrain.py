"""Smooth analytic terrain: a plane plus Gaussian hills and valleys, evaluable anywhere."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray


@dataclass(frozen=True, eq=False)
class Terrain:
    """``h(x, y) = base + gx (x - x0) + gy (y - y0) + sum amp exp(-d^2 / (2 sigma^2))``.

    Coordinates are CRS metres; ``hills`` rows are ``(cx, cy, amplitude, sigma)``.
    Heights are ellipsoidal (WGS 84) metres.
    """

    base: float
    origin: tuple[float, float]
    slope: tuple[float, float]
    hills: NDArray[np.float64]

    def height(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
        xa = np.asarray(x, dtype=np.float64)
        ya = np.asarray(y, dtype=np.float64)
        h = (
            self.base
            + self.slope[0] * (xa - self.origin[0])
            + self.slope[1] * (ya - self.origin[1])
        )
        for cx, cy, amp, sigma in self.hills:
            h = h + amp * np.exp(-((xa - cx) ** 2 + (ya - cy) ** 2) / (2.0 * sigma**2))
        return np.asarray(h, dtype=np.float64)

    def to_dict(self) -> dict[str, Any]:
        return {
            "model": "plane+gaussians",
            "base": self.base,
            "origin": list(self.origin),
            "slope": list(self.slope),
            "hills": [[float(v) for v in row] for row in self.hills],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Terrain:
        hills = np.asarray(d["hills"], dtype=np.float64).reshape(-1, 4)
        return cls(
            base=float(d["base"]),
            origin=(float(d["origin"][0]), float(d["origin"][1])),
            slope=(float(d["slope"][0]), float(d["slope"][1])),
            hills=hills,
        )


def random_terrain(
    rng: np.random.Generator,
    bounds: tuple[float, float, float, float],
    *,
    base: float = 150.0,
    relief: tuple[float, float] = (6.0, 12.0),
) -> Terrain:
    """A terrain over ``bounds`` (xmin, ymin, xmax, ymax) whose relief lies in ``relief`` metres."""
    xmin, ymin, xmax, ymax = bounds
    size = max(xmax - xmin, ymax - ymin)
    cx, cy = (xmin + xmax) / 2, (ymin + ymax) / 2
    direction = rng.uniform(0, 2 * np.pi)
    grade = rng.uniform(0.03, 0.08)
    n_hills = int(rng.integers(3, 6))
    hills = np.column_stack(
        [
            rng.uniform(xmin, xmax, n_hills),
            rng.uniform(ymin, ymax, n_hills),
            rng.uniform(1.5, 4.0, n_hills) * rng.choice([-1.0, 1.0], n_hills),
            rng.uniform(0.12, 0.3, n_hills) * size,
        ]
    )
    raw = Terrain(base, (cx, cy), (grade * np.cos(direction), grade * np.sin(direction)), hills)
    gx, gy = np.meshgrid(np.linspace(xmin, xmax, 61), np.linspace(ymin, ymax, 61))
    h = raw.height(gx, gy) - base
    target = rng.uniform(*relief)
    scale = target / float(h.max() - h.min())
    hills_scaled = hills.copy()
    hills_scaled[:, 2] *= scale
    return Terrain(
        base,
        (cx, cy),
        (raw.slope[0] * scale, raw.slope[1] * scale),
        hills_scaled,
    )
