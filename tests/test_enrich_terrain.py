"""The terrain step's point selections against plain per-square references: the lowest
return of each square, the point nearest each square's centre, and CSF square by square
on the points sorted by x, y, z (ties and duplicates included)."""

from __future__ import annotations

import numpy as np

from standgrid.enrichment import terrain
from standgrid.enrichment.ground import classify_ground
from standgrid.partition.lattice import lowest_in_squares

LATTICE = (0.3, -0.7)


def tied_points(n: int, seed: int) -> np.ndarray:
    """Points on a coarse 1/8 m grid (many ties in x, y and z), some repeated exactly."""
    rng = np.random.default_rng(seed)
    xyz = np.round(rng.uniform((0, 0, 100), (30, 20, 101), (n, 3)) * 8) / 8
    xyz += np.array([600_000.0, 5_700_000.0, 0.0])
    return np.concatenate([xyz, xyz[rng.integers(0, n, n // 20)]])[rng.permutation(n + n // 20)]


def squares_of(xyz: np.ndarray, size: float) -> list[tuple[int, int]]:
    return [
        (int(np.floor((x - LATTICE[0]) / size)), int(np.floor((y - LATTICE[1]) / size)))
        for x, y in xyz[:, :2]
    ]


def test_lowest_is_every_point_at_its_squares_minimum() -> None:
    xyz = tied_points(20_000, seed=1)
    squares = squares_of(xyz, 0.25)
    low: dict[tuple[int, int], float] = {}
    for square, z in zip(squares, xyz[:, 2], strict=True):
        low[square] = min(z, low.get(square, np.inf))
    expected = [
        k for k, (square, z) in enumerate(zip(squares, xyz[:, 2], strict=True)) if z == low[square]
    ]
    assert lowest_in_squares(xyz, 0.25, LATTICE).tolist() == expected


def test_thin_keeps_the_point_nearest_each_centre_whatever_the_order() -> None:
    xyz = tied_points(20_000, seed=2)
    spacing = 0.5
    best: dict[tuple[int, int], tuple[float, float, float, float, int]] = {}
    for k, square in enumerate(squares_of(xyz, spacing)):
        offset = (xyz[k, :2] - LATTICE) / spacing - (
            np.floor((xyz[k, :2] - LATTICE) / spacing) + 0.5
        )
        rank = (float((offset**2).sum()), *map(float, xyz[k]), k)  # ties: x, y, z, then row
        best[square] = min(rank, best.get(square, rank))
    expected = xyz[sorted(rank[-1] for rank in best.values())]
    assert np.array_equal(terrain.thin(xyz, spacing, LATTICE), expected)
    shuffled = terrain.thin(xyz[::-1], spacing, LATTICE)
    assert np.array_equal(np.unique(shuffled, axis=0), np.unique(expected, axis=0))


def test_csf_squares_see_their_points_sorted_by_x_y_z() -> None:
    """Each square's CSF run gets exactly the points within the halo of it, in x, y, z
    order (a reference that selects and sorts square by square)."""
    rng = np.random.default_rng(3)
    n = 6_000
    x, y = rng.uniform(0, 50, n), rng.uniform(0, 45, n)
    z = 0.3 * x + np.sin(y / 5) + np.where(rng.random(n) < 0.5, 0.0, rng.uniform(2, 15, n))
    xyz = np.round(np.column_stack([x, y, z]) * 100) / 100 + (600_000.0, 5_700_000.0, 0.0)
    side, halo = terrain.GROUND_SQUARE_M, terrain.GROUND_HALO_M
    # points on the halos' edges (computed as the squares' bounds are), stacked returns
    # (same x, y, other z) and exact duplicates
    ix = np.floor((xyz[:500, 0] - LATTICE[0]) / side)
    xyz[:250, 0] = LATTICE[0] + ix[:250] * side - halo
    xyz[250:500, 0] = LATTICE[0] + ix[250:] * side + side + halo
    stacked = xyz[500:1500].copy()
    stacked[:, 2] -= rng.uniform(0.01, 3.0, len(stacked))
    xyz = np.concatenate([xyz, stacked, xyz[:300]])[rng.permutation(n + 1300)]
    expected = np.zeros(len(xyz), dtype=bool)
    owners = squares_of(xyz, side)
    for ix, iy in sorted(set(owners)):
        x0, y0 = LATTICE[0] + ix * side, LATTICE[1] + iy * side
        px, py = xyz[:, 0], xyz[:, 1]
        near = np.flatnonzero(
            (px >= x0 - halo)
            & (px < x0 + side + halo)
            & (py >= y0 - halo)
            & (py < y0 + side + halo)
        )
        order = near[np.lexsort((xyz[near, 2], xyz[near, 1], xyz[near, 0]))]
        labels = classify_ground(xyz[order], cloth_resolution=0.5, rigidness=1)
        mine = np.array([owners[k] == (ix, iy) for k in order])
        expected[order[mine]] = labels[mine]
    assert 0 < expected.sum() < len(xyz)
    found = terrain._classify(xyz, LATTICE, 0.5, 1, None)
    assert np.array_equal(found, expected)
