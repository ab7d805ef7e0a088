"""Simulated on-board elevation maps: the terrain truth seen from each payload, plus a known
error (a vertical bias and Gaussian noise), in the payload's base frame."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from standgrid.geometry import Matrix4, transform_points
from standgrid.simulate.chain import FrameChain
from standgrid.simulate.terrain import Terrain


@dataclass(frozen=True)
class ElevationMapModel:
    """A square height grid of ``2 half_size`` m around the robot at ``resolution`` m; each
    height is the terrain's along the base z axis plus ``bias`` and ``N(0, noise_std)``."""

    resolution: float = 0.25
    half_size: float = 10.0
    bias: float = 0.05
    noise_std: float = 0.03

    def truth(self) -> dict[str, Any]:
        """What truth.json says of the maps (their error against the terrain truth)."""
        return {
            **{f"{k}_m": v for k, v in asdict(self).items()},
            "frame": "payload base frame at the true pose; heights along its z axis",
            "error": "height = terrain + bias + N(0, noise_std), per cell, independent",
        }


def elevation_grid(
    model: ElevationMapModel,
    terrain: Terrain,
    chain: FrameChain,
    true_pose: Matrix4,
    rng: np.random.Generator,
) -> tuple[NDArray[np.float32], tuple[float, float]]:
    """The heights (row 0 at the lowest y) and the grid's lower-left corner, base frame."""
    n = round(2 * model.half_size / model.resolution)
    centres = -model.half_size + (np.arange(n) + 0.5) * model.resolution
    u, v = np.meshgrid(centres, centres)  # row i: y = centres[i]
    base = np.column_stack([u.ravel(), v.ravel(), np.zeros(u.size)])
    to_crs = chain.map_to_crs
    for _ in range(4):  # Newton along the base z axis (tilted by a few degrees at most)
        crs = to_crs(transform_points(true_pose, base))
        above = crs[:, 2] - terrain.height(crs[:, 0], crs[:, 1])
        base[:, 2] -= above / true_pose[2, 2]
    heights = base[:, 2] + model.bias + rng.normal(0.0, model.noise_std, len(base))
    return heights.reshape(n, n).astype(np.float32), (-model.half_size, -model.half_size)
