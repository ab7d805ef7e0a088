"""Maps a payload carries besides its cloud: an elevation map and a volumetric map.

Both are computed on board and attached to a payload by stamp (docs/FORMATS.md, "Derived
maps"): ``payloads/elevation/elevation_<sec>_<nsec>.{npz,tif,png}`` and
``payloads/volumetric/voxels_<sec>_<nsec>.{npz,bt,ot}``. A map's grid lies in its own frame,
placed in the payload's base frame by ``pose`` (T_base_grid, identity by default), so it is
placed into a CRS exactly as the payload's points are. An elevation GeoTIFF carrying a
projected CRS is in that CRS instead. Every reader raises :class:`DerivedMapFormatError`
naming the file.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from standgrid.crs import CRS
from standgrid.errors import DerivedMapFormatError, FormatError

#: File suffixes (without the dot) of each kind of map.
ELEVATION_EXTENSIONS = frozenset({"npz", "tif", "tiff", "png"})
VOLUMETRIC_EXTENSIONS = frozenset({"npz", "bt", "ot"})
#: Where each kind lives in a mission folder, and its file-name prefix.
ELEVATION_FOLDER, ELEVATION_PREFIX = "payloads/elevation", "elevation"
VOLUMETRIC_FOLDER, VOLUMETRIC_PREFIX = "payloads/volumetric", "voxels"

VoxelKind = Literal["occupancy", "tsdf"]


def _identity() -> NDArray[np.float64]:
    return np.eye(4)


@dataclass(frozen=True, eq=False)
class ElevationMap:
    """A 2.5-D height grid: ``heights[i, j]`` (NaN: no data) is the height of the cell centred
    at ``origin + ((j + 0.5) r, (i + 0.5) r)`` (row 0 at the lowest y) in the grid frame,
    which ``pose`` (T_base_grid) places in the payload's base frame; with ``crs`` the grid
    is in that projected CRS (``pose`` identity)."""

    heights: NDArray[np.float32]
    resolution: float
    origin: tuple[float, float]
    pose: NDArray[np.float64] = field(default_factory=_identity)
    crs: CRS | None = None
    path: Path | None = None

    def cell_points(self) -> NDArray[np.float64]:
        """The cells holding a height as points ``(N, 3)``: in the base frame (or the CRS)."""
        rows, cols = np.nonzero(np.isfinite(self.heights))
        r = self.resolution
        pts = np.column_stack(
            [
                self.origin[0] + (cols + 0.5) * r,
                self.origin[1] + (rows + 0.5) * r,
                self.heights[rows, cols].astype(np.float64),
            ]
        )
        return _transformed(pts, self.pose)


@dataclass(frozen=True, eq=False)
class VoxelGrid:
    """A volumetric map: ``values[i, j, k]`` of the voxel centred at ``origin + (ijk + 0.5) s``
    in the grid frame (``pose``: T_base_grid). ``occupancy``: probabilities in [0, 1] (NaN:
    unknown); ``tsdf``: truncated signed distances (m, NaN: unobserved)."""

    values: NDArray[np.float32]
    voxel_size: float
    origin: tuple[float, float, float]
    kind: VoxelKind
    pose: NDArray[np.float64] = field(default_factory=_identity)
    path: Path | None = None

    def corners(self) -> NDArray[np.float64]:
        """The grid box's 8 corners in the base frame ``(8, 3)``."""
        lo = np.asarray(self.origin, np.float64)
        hi = lo + np.asarray(self.values.shape, np.float64) * self.voxel_size
        box = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        return _transformed(box, self.pose)

    def occupied_points(self, threshold: float = 0.5) -> NDArray[np.float64]:
        """Centres of the occupied voxels (occupancy above ``threshold``; TSDF: within half a
        voxel of the surface) in the base frame ``(N, 3)``."""
        with np.errstate(invalid="ignore"):
            if self.kind == "occupancy":
                hit = np.asarray(self.values > threshold)
            else:
                hit = np.asarray(np.abs(self.values) <= self.voxel_size / 2)
        ijk = np.argwhere(hit).astype(np.float64)
        pts = np.asarray(self.origin, np.float64) + (ijk + 0.5) * self.voxel_size
        return _transformed(pts, self.pose)


@dataclass(frozen=True, eq=False)
class OctreeMap:
    """An OctoMap (``.bt``/``.ot``, read with octomap-python): its occupied leaves' centres
    and its metric box in the grid frame (``pose``: T_base_grid, from a JSON sidecar)."""

    occupied: NDArray[np.float64]
    resolution: float
    box: tuple[tuple[float, float, float], tuple[float, float, float]]
    pose: NDArray[np.float64] = field(default_factory=_identity)
    path: Path | None = None
    kind: Literal["octomap"] = "octomap"

    @property
    def voxel_size(self) -> float:
        return self.resolution

    def corners(self) -> NDArray[np.float64]:
        """The octree's metric box's 8 corners in the base frame ``(8, 3)``."""
        lo, hi = self.box
        box = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        return _transformed(box, self.pose)

    def occupied_points(self) -> NDArray[np.float64]:
        """Centres of the occupied leaves in the base frame ``(N, 3)``."""
        return _transformed(self.occupied, self.pose)


def _transformed(pts: NDArray[np.float64], pose: NDArray[np.float64]) -> NDArray[np.float64]:
    if np.array_equal(pose, np.eye(4)):
        return pts
    return np.asarray(pts @ pose[:3, :3].T + pose[:3, 3], np.float64)


# --- reading ----------------------------------------------------------------------------


def read_elevation_map(path: str | Path) -> ElevationMap:
    """An elevation map file: ``.npz`` (``heights``, ``resolution``, ``origin``, optional
    ``pose``), a GeoTIFF (its geotransform in the payload frame, or its projected CRS), or a
    16-bit PNG with a JSON sidecar of the same stem."""
    p = Path(path)
    suffix = p.suffix.lower().lstrip(".")
    if suffix == "npz":
        return _elevation_npz(p)
    if suffix in ("tif", "tiff"):
        return _elevation_tif(p)
    if suffix == "png":
        return _elevation_png(p)
    raise DerivedMapFormatError(
        f"not an elevation map format (.{'/.'.join(sorted(ELEVATION_EXTENSIONS))})", path=p
    )


def read_voxel_grid(path: str | Path) -> VoxelGrid | OctreeMap:
    """A volumetric map file: ``.npz`` (``occupancy`` or ``tsdf``, ``voxel_size``, ``origin``,
    optional ``pose``), or an OctoMap ``.bt``/``.ot`` (with octomap-python, the optional
    ``octomap`` extra; its optional JSON sidecar of the same stem gives ``pose``)."""
    p = Path(path)
    suffix = p.suffix.lower().lstrip(".")
    if suffix in ("bt", "ot"):
        return _octomap(p)
    if suffix != "npz":
        raise DerivedMapFormatError("not a volumetric map format (.npz, .bt, .ot)", path=p)
    data = _npz(p)
    kinds = [k for k in ("occupancy", "tsdf") if k in data]
    if len(kinds) != 1:
        raise DerivedMapFormatError(
            f"a voxel grid holds exactly one of 'occupancy' or 'tsdf' (has {sorted(data)})",
            path=p,
        )
    kind: VoxelKind = "occupancy" if kinds[0] == "occupancy" else "tsdf"
    values = np.asarray(data[kind])
    if values.ndim != 3 or not all(values.shape) or not np.issubdtype(values.dtype, np.number):
        raise DerivedMapFormatError(
            f"'{kind}' must be a non-empty 3-D numeric array, got shape {values.shape}", path=p
        )
    size = _positive(data, "voxel_size", p)
    origin = _vector(data, "origin", 3, p)
    return VoxelGrid(
        values.astype(np.float32),
        size,
        (origin[0], origin[1], origin[2]),
        kind,
        _pose(data.get("pose"), p),
        p,
    )


def _octomap(p: Path) -> OctreeMap:
    try:
        import octomap
    except ImportError:
        raise DerivedMapFormatError(
            "reading an OctoMap needs octomap-python (pip install 'standgrid[octomap]'); the "
            "file is kept with its payload",
            path=p,
        ) from None
    if not p.is_file():
        raise DerivedMapFormatError("no such file", path=p)
    if p.suffix.lower() == ".bt":
        tree = octomap.OcTree(0.1)  # the file's resolution replaces it
        if not tree.readBinary(str(p).encode()):
            raise DerivedMapFormatError("not an OctoMap binary (.bt) file", path=p)
    else:
        try:
            tree = octomap.OcTree.read(str(p).encode())
        except OSError as exc:
            raise DerivedMapFormatError(f"not an OctoMap (.ot) file: {exc}", path=p) from exc
    occupied, _ = tree.extractPointCloud()
    lo = tuple(float(v) for v in tree.getMetricMin())
    hi = tuple(float(v) for v in tree.getMetricMax())
    sidecar = p.with_suffix(".json")
    pose = np.eye(4)
    if sidecar.is_file():
        try:
            meta = json.loads(sidecar.read_text())
        except (OSError, ValueError) as exc:
            raise DerivedMapFormatError(f"unreadable JSON sidecar: {exc}", path=sidecar) from exc
        pose = _pose(meta.get("pose") if isinstance(meta, dict) else None, sidecar)
    return OctreeMap(
        np.asarray(occupied, np.float64).reshape(-1, 3),
        float(tree.getResolution()),
        ((lo[0], lo[1], lo[2]), (hi[0], hi[1], hi[2])),
        pose,
        p,
    )


def _npz(p: Path) -> dict[str, Any]:
    try:
        with np.load(p, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError) as exc:
        raise DerivedMapFormatError(f"not a readable .npz: {exc}", path=p) from exc


def _positive(data: dict[str, Any], key: str, p: Path) -> float:
    if key not in data:
        raise DerivedMapFormatError(f"missing '{key}' (has {sorted(data)})", path=p)
    try:
        value = float(np.asarray(data[key], np.float64).reshape(()))
    except (TypeError, ValueError) as exc:
        raise DerivedMapFormatError(f"'{key}' must be one number", path=p) from exc
    if not (np.isfinite(value) and value > 0):
        raise DerivedMapFormatError(f"'{key}' must be > 0, got {value}", path=p)
    return value


def _vector(data: dict[str, Any], key: str, n: int, p: Path) -> list[float]:
    if key not in data:
        raise DerivedMapFormatError(f"missing '{key}' (has {sorted(data)})", path=p)
    try:
        values = np.asarray(data[key], np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise DerivedMapFormatError(f"'{key}' must be {n} numbers", path=p) from exc
    if values.shape != (n,) or not np.isfinite(values).all():
        raise DerivedMapFormatError(f"'{key}' must be {n} finite numbers, got {values}", path=p)
    return [float(v) for v in values]


def _pose(value: Any, p: Path) -> NDArray[np.float64]:
    if value is None:
        return np.eye(4)
    try:
        pose = np.asarray(value, np.float64)
    except (TypeError, ValueError) as exc:
        raise DerivedMapFormatError("'pose' must be a 4x4 matrix", path=p) from exc
    rigid = pose.shape == (4, 4) and bool(np.isfinite(pose).all())
    rigid = rigid and bool(np.allclose(pose[3], [0, 0, 0, 1]))
    rigid = rigid and bool(np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-6))
    if not rigid:
        raise DerivedMapFormatError("'pose' must be a rigid 4x4 transform (T_base_grid)", path=p)
    return pose


def _heights(values: Any, p: Path) -> NDArray[np.float32]:
    heights = np.asarray(values)
    if heights.ndim != 2 or not all(heights.shape) or not np.issubdtype(heights.dtype, np.number):
        raise DerivedMapFormatError(
            f"'heights' must be a non-empty 2-D numeric array, got shape {heights.shape}", path=p
        )
    out = heights.astype(np.float32)
    if np.isinf(out).any():
        raise DerivedMapFormatError("'heights' holds infinite values (NaN: no data)", path=p)
    return out


def _elevation_npz(p: Path) -> ElevationMap:
    data = _npz(p)
    if "heights" not in data:
        raise DerivedMapFormatError(f"missing 'heights' (has {sorted(data)})", path=p)
    origin = _vector(data, "origin", 2, p)
    return ElevationMap(
        _heights(data["heights"], p),
        _positive(data, "resolution", p),
        (origin[0], origin[1]),
        _pose(data.get("pose"), p),
        None,
        p,
    )


def _elevation_tif(p: Path) -> ElevationMap:
    from standgrid.geotiff import read_raster

    try:
        raster = read_raster(p)
    except FormatError as exc:
        raise DerivedMapFormatError(exc.message, path=p) from exc
    crs = raster.grid.crs
    if crs is not None and not crs.is_projected:
        raise DerivedMapFormatError(
            f"the elevation map's CRS {crs.name!r} is not projected (x/y must be metres)", path=p
        )
    grid = raster.grid
    heights = _heights(np.flipud(raster.array), p)  # GeoTIFF row 0 is the northern row
    return ElevationMap(heights, grid.pixel_size, (grid.x0, grid.y0), np.eye(4), crs, p)


def png_sidecar(path: Path) -> Path:
    """The JSON sidecar of a PNG elevation map: same stem, ``.json``."""
    return path.with_suffix(".json")


def _elevation_png(p: Path) -> ElevationMap:
    from PIL import Image, UnidentifiedImageError

    sidecar = png_sidecar(p)
    try:
        meta = json.loads(sidecar.read_text())
    except FileNotFoundError:
        raise DerivedMapFormatError(
            f"a PNG elevation map needs its JSON sidecar {sidecar.name}", path=p
        ) from None
    except (OSError, ValueError) as exc:
        raise DerivedMapFormatError(f"unreadable JSON sidecar: {exc}", path=sidecar) from exc
    if not isinstance(meta, dict):
        raise DerivedMapFormatError("the sidecar must be a JSON object", path=sidecar)
    try:
        with Image.open(p) as image:
            values = np.asarray(image)
    except (OSError, UnidentifiedImageError) as exc:
        raise DerivedMapFormatError(f"not a readable PNG: {exc}", path=p) from exc
    if values.ndim != 2 or values.dtype not in (np.uint16, np.int32, np.uint8):
        raise DerivedMapFormatError(
            f"a PNG elevation map is one grey 16-bit band, got {values.dtype} {values.shape}",
            path=p,
        )
    resolution = _positive(meta, "resolution", sidecar)
    origin = _vector(meta, "origin", 2, sidecar)
    scale = _positive(meta, "scale", sidecar)
    offset = float(meta.get("offset", 0.0))
    nodata = meta.get("nodata", 0)
    heights = offset + scale * values.astype(np.float64)
    if nodata is not None:
        heights[values == int(nodata)] = np.nan
    heights = np.flipud(heights)  # PNG row 0 is the top row (the largest y)
    pose = _pose(meta.get("pose"), sidecar)
    return ElevationMap(
        heights.astype(np.float32), resolution, (origin[0], origin[1]), pose, None, p
    )


# --- writing ----------------------------------------------------------------------------


def write_elevation_npz(
    path: str | Path,
    heights: NDArray[np.floating],
    resolution: float,
    origin: tuple[float, float],
    pose: NDArray[np.float64] | None = None,
) -> Path:
    """Write an elevation map ``.npz`` (the layout :func:`read_elevation_map` reads)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, Any] = {
        "heights": np.asarray(heights, np.float32),
        "resolution": np.float64(resolution),
        "origin": np.asarray(origin, np.float64),
    }
    if pose is not None:
        arrays["pose"] = np.asarray(pose, np.float64)
    with p.open("wb") as f:
        np.savez_compressed(f, **arrays)
    return p


def write_voxel_npz(
    path: str | Path,
    values: NDArray[np.floating],
    voxel_size: float,
    origin: tuple[float, float, float],
    kind: VoxelKind = "occupancy",
    pose: NDArray[np.float64] | None = None,
) -> Path:
    """Write a voxel grid ``.npz`` (the layout :func:`read_voxel_grid` reads)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, Any] = {
        kind: np.asarray(values, np.float32),
        "voxel_size": np.float64(voxel_size),
        "origin": np.asarray(origin, np.float64),
    }
    if pose is not None:
        arrays["pose"] = np.asarray(pose, np.float64)
    with p.open("wb") as f:
        np.savez_compressed(f, **arrays)
    return p
