"""What persists between visits, from one mission's own points: the ground and the stems.

Read once, payload by payload, in the mission's own frame (its SLAM map, or the projected
CRS of plain scans), so that nothing depends on where GNSS put it. Each payload keeps its
lowest point per ground cell (the ground) and the points from 0.3 to 3.8 m above its own
lowest (where stems are), thinned to a voxel; the mission's ground is then the lowest of
every cell, cells standing more than a step above their neighbours (a stem's foot, a log)
dropped, and the stems are found by :func:`standgrid.features.stems.find_stems` in the kept
points normalised to that ground. Crowns are left out: they grow and move between visits.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from standgrid.features.stems import StemOptions, find_stems
from standgrid.mission.model import Mission

FloatArray = NDArray[np.float64]

#: Ground cells (m); kept points go from ``BAND[0]`` to ``BAND[1]`` above a payload's lowest.
GROUND_CELL_M = 1.0
BAND = (0.3, 3.8)
#: Kept points are thinned to one per voxel (m): the stems that tie missions together are
#: the bigger ones, whose circles still get tens of points.
VOXEL_M = 0.02
#: A ground cell higher than its neighbours' median by more than this (m) is not ground.
GROUND_STEP_M = 0.5


@dataclass(frozen=True, eq=False)
class Landmarks:
    """One mission's persistent features, in its own frame (``frame``: "map" or "crs").

    ``stems``: (n, 4) x, y, z at breast height and DBH (m); ``ground``: (m, 3) one lowest
    point per ground cell; ``points``: the kept band and ground points (for fine
    registration); ``nodes``: the trajectory (or scan positions), (k, 3)."""

    name: str
    frame: str
    stems: FloatArray
    ground: FloatArray
    points: FloatArray
    nodes: FloatArray

    @property
    def n_stems(self) -> int:
        return len(self.stems)


def _cells(xyz: FloatArray) -> NDArray[np.int64]:
    ij = np.floor(xyz[:, :2] / GROUND_CELL_M).astype(np.int64)
    return ij[:, 0] * 2_000_003 + ij[:, 1]


def _lowest_per_cell(xyz: FloatArray) -> tuple[NDArray[np.int64], FloatArray]:
    """The cell keys and the lowest point of each occupied cell."""
    keys = _cells(xyz)
    order = np.lexsort((xyz[:, 2], keys))
    first = np.r_[True, keys[order][1:] != keys[order][:-1]]
    rows = order[first]
    return keys[rows], xyz[rows]


def _thin(xyz: FloatArray, voxel: float) -> FloatArray:
    if not len(xyz):
        return xyz
    q = np.floor(xyz / voxel).astype(np.int64)
    q -= q.min(axis=0)
    span = q.max(axis=0) + 1
    key = (q[:, 0] * span[1] + q[:, 1]) * span[2] + q[:, 2]  # < 2^63 for any mission
    _, rows = np.unique(key, return_index=True)
    return xyz[np.sort(rows)]


def payload_keep(xyz: FloatArray) -> tuple[FloatArray, FloatArray]:
    """One payload's lowest point per ground cell, and its thinned points in the stem band."""
    if not len(xyz):
        return np.zeros((0, 3)), np.zeros((0, 3))
    keys = _cells(xyz)
    cells, inverse = np.unique(keys, return_inverse=True)
    floor = np.full(len(cells), np.inf)
    np.minimum.at(floor, inverse, xyz[:, 2])
    lowest_row = np.full(len(cells), -1, dtype=np.int64)
    at_floor = np.flatnonzero(xyz[:, 2] == floor[inverse])
    lowest_row[inverse[at_floor]] = at_floor
    lowest = xyz[lowest_row]
    h = xyz[:, 2] - floor[inverse]
    band = xyz[(h >= BAND[0]) & (h <= BAND[1])]
    return lowest, _thin(band, VOXEL_M)


def ground_grid(
    lowest: FloatArray,
) -> tuple[FloatArray, tuple[NDArray[np.int64], FloatArray]]:
    """The mission's ground: the lowest of every cell, steps above the neighbours dropped.
    Returns the ground points and a cell -> height lookup."""
    keys, ground = _lowest_per_cell(lowest)
    ij = np.floor(ground[:, :2] / GROUND_CELL_M).astype(np.int64)
    lo = ij.min(axis=0)
    shape = tuple(ij.max(axis=0) - lo + 1)
    grid = np.full(shape, np.nan)
    grid[ij[:, 0] - lo[0], ij[:, 1] - lo[1]] = ground[:, 2]
    filled = np.where(np.isfinite(grid), grid, np.nanmedian(grid))
    med = ndimage.median_filter(filled, size=5, mode="nearest")
    ok = ground[:, 2] <= med[ij[:, 0] - lo[0], ij[:, 1] - lo[1]] + GROUND_STEP_M
    keys, ground = keys[ok], ground[ok]
    return ground, (keys, ground[:, 2].copy())


def heights_above(xyz: FloatArray, floor: tuple[NDArray[np.int64], FloatArray]) -> FloatArray:
    """Height of each point above its ground cell (NaN where the cell has no ground);
    ``floor``: sorted cell keys and their heights."""
    keys, heights = floor
    if not len(keys):
        return np.full(len(xyz), np.nan)
    cells = _cells(xyz)
    at = np.clip(np.searchsorted(keys, cells), 0, len(keys) - 1)
    return xyz[:, 2] - np.where(keys[at] == cells, heights[at], np.nan)


def landmarks_from_points(
    name: str,
    frame: str,
    chunks: list[tuple[FloatArray, FloatArray]],
    nodes: FloatArray,
    stem_options: StemOptions | None = None,
) -> Landmarks:
    """Landmarks from the per-payload ``(lowest, band)`` pairs of :func:`payload_keep`."""
    lowest = np.concatenate([c[0] for c in chunks]) if chunks else np.zeros((0, 3))
    band = np.concatenate([c[1] for c in chunks]) if chunks else np.zeros((0, 3))
    if not len(lowest):
        empty = np.zeros((0, 3))
        return Landmarks(name, frame, np.zeros((0, 4)), empty, empty, nodes)
    ground, floor = ground_grid(lowest)
    band = _thin(band, VOXEL_M)  # overlapping payloads saw the same surfaces
    h = heights_above(band, floor)
    options = stem_options or StemOptions()
    # the slices find_stems cuts (the rest of the band is kept for fine registration)
    centres = options.band_heights()
    nearest = np.abs(h[:, None] - centres[None, :]).min(axis=1) if len(h) else h
    ok = np.isfinite(h) & (nearest <= options.band_half_width)
    stems = find_stems(band[ok], h[ok], options=options).table
    if len(stems):
        sx, sy = stems["stem_x"].to_numpy(), stems["stem_y"].to_numpy()
        # a point at height 0 stands -(ground) above the ground
        zg = -heights_above(np.column_stack([sx, sy, np.zeros(len(sx))]), floor)
        zg = np.where(np.isfinite(zg), zg, np.nanmedian(ground[:, 2]))
        table = np.column_stack([sx, sy, zg + options.breast_height, stems["dbh_m"].to_numpy()])
    else:
        table = np.zeros((0, 4))
    kept = np.concatenate([band[np.isfinite(h)], ground])
    # as the cache keeps them (float32 about the first node): a mission's landmarks are the
    # same whether found now or read back, and so is every registration made from them
    origin = _origin(nodes)
    kept = (kept - origin).astype(np.float32).astype(np.float64) + origin
    return Landmarks(name, frame, table, ground, kept, nodes)


def _origin(nodes: FloatArray) -> FloatArray:
    return np.asarray(nodes[0], dtype=np.float64) if len(nodes) else np.zeros(3)


def mission_landmarks(mission: Mission, stem_options: StemOptions | None = None) -> Landmarks:
    """The landmarks of a mission in its own frame: the map frame of a SLAM mission, the
    projected CRS of plain scans (``frame`` "crs")."""
    chunks = []
    if mission.is_projected:
        frame = "crs"
        for payload in mission.payloads:
            if payload.kind == "point_cloud":
                chunks.append(payload_keep(mission.load_projected(payload).xyz))
        nodes = np.array([c[0].mean(axis=0) for c in chunks if len(c[0])]).reshape(-1, 3)
    else:
        frame = "map"
        for _payload, cloud in mission.iter_payload_clouds("map"):
            chunks.append(payload_keep(cloud.xyz))
        nodes = mission.trajectory()[1]
    return landmarks_from_points(mission.name, frame, chunks, nodes, stem_options)


def landmarks_key(mission: Mission) -> str:
    """A digest of what the landmarks are made from: the payload files (path, size, time)
    and the pose graph's."""
    import hashlib

    digest = hashlib.sha256(b"standgrid.align.landmarks/1")  # the cache's tag, kept
    digest.update(f"{mission.name};".encode())
    files = [p.path for p in mission.payloads]
    graph = getattr(mission.graph, "source", None)
    if graph is not None:
        files.append(graph)
    for path in sorted(str(f) for f in files):
        try:
            st = Path(path).stat()
        except OSError:
            continue
        digest.update(f"{Path(path).name}:{st.st_size}:{st.st_mtime_ns};".encode())
    return digest.hexdigest()


def save_landmarks(marks: Landmarks, key: str, path: Path) -> None:
    """Write ``marks`` (kept points as float32 about their first node) to ``path`` (.npz)."""
    origin = _origin(marks.nodes)
    with open(path, "wb") as f:
        np.savez(
            f,
            key=np.array(key),
            name=np.array(marks.name),
            frame=np.array(marks.frame),
            origin=origin,
            stems=marks.stems,
            ground=marks.ground,
            nodes=marks.nodes,
            points=(marks.points - origin).astype(np.float32),
        )


def load_landmarks(path: Path, key: str) -> Landmarks | None:
    """The landmarks saved at ``path`` when made from the same files (``key``), else None."""
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) != key:
                return None
            origin = data["origin"]
            return Landmarks(
                str(data["name"]),
                str(data["frame"]),
                data["stems"],
                data["ground"],
                data["points"].astype(np.float64) + origin,
                data["nodes"],
            )
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
        return None  # a damaged cache is no cache: the landmarks are found again
