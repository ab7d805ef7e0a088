"""Ground truth written beside a simulated mission, and read back with :func:`load_truth`.

``<out_root>/truth/<mission>/``:
  truth.json        crs, lla_ref, T_map_enu (4x4), seed, epoch, date, terrain, stand bounds, ...
  trees.csv         tree_id, x, y, z_ground, dbh_m, height_m, crown_base_m, crown_radius_m,
                    species, status; then, for stands other than a plantation of vertical
                    overstorey trees (when left out, read as those defaults): kind,
                    lean_deg, lean_azimuth_deg, fork_height_m (empty: none), x_bh, y_bh,
                    foliage_density (see :class:`~standgrid.simulate.forest.Trees`)
  shrubs.csv        x, y, z_ground, radius_m, height_m (understory)
  true_poses.csv    the true T_map_base of every node (pose CSV format)
  gnss_truth.csv    sec, nsec, true antenna x, y, z (CRS), outlier flag of every written fix
  payload_points/   (missions cut from a real scan) original CRS coordinates and point
                    indices per payload: points_<sec>_<nsec>.npy, index_<sec>_<nsec>.npy
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from standgrid.errors import FormatError, MissionNotFoundError, StandgridError
from standgrid.mission.poses_csv import PoseTable, read_poses_csv
from standgrid.simulate.chain import FrameChain
from standgrid.simulate.forest import Shrubs, Trees
from standgrid.simulate.terrain import Terrain
from standgrid.stamps import Stamp

TREE_COLUMNS = (
    "tree_id",
    "x",
    "y",
    "z_ground",
    "dbh_m",
    "height_m",
    "crown_base_m",
    "crown_radius_m",
    "species",
    "status",
)
#: Columns of a mixed stand, after :data:`TREE_COLUMNS`.
STAND_COLUMNS = (
    "kind",
    "lean_deg",
    "lean_azimuth_deg",
    "fork_height_m",
    "x_bh",
    "y_bh",
    "foliage_density",
)
SHRUB_COLUMNS = ("x", "y", "z_ground", "radius_m", "height_m")
GNSS_TRUTH_HEADER = "sec,nsec,x,y,z,outlier"


class TruthLookupError(StandgridError, KeyError):
    """The truth holds nothing for the asked stamp (a ``KeyError``, so a ``LookupError``)."""


def _open_error(exc: OSError, path: Path, what: str) -> StandgridError:
    """A missing file -> :class:`MissionNotFoundError`; any other OS error -> FormatError."""
    if isinstance(exc, FileNotFoundError):
        return MissionNotFoundError(f"{what} not found", path=path)
    return FormatError(f"cannot read {what}: {exc.strerror or exc}", path=path)


@dataclass(eq=False)
class Truth:
    """Everything known about a simulated (or scan-derived) mission."""

    path: Path
    name: str
    kind: str
    crs: str
    lla_ref: tuple[float, float, float]
    T_map_enu: NDArray[np.float64]
    seed: int
    epoch: int
    date: str
    bounds: tuple[float, float, float, float]
    terrain: Terrain | None
    trees: Trees | None
    shrubs: Shrubs | None
    true_poses: PoseTable
    gnss_stamps_ns: NDArray[np.int64]
    gnss_true_xyz: NDArray[np.float64]
    gnss_outlier: NDArray[np.bool_]
    info: dict[str, Any] = field(default_factory=dict)

    def terrain_height(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
        """True ground height (ellipsoidal m) at CRS ``(x, y)``."""
        if self.terrain is None:
            raise ValueError(f"{self.path}: this truth has no analytic terrain (kind {self.kind})")
        return self.terrain.height(x, y)

    def chain(self) -> FrameChain:
        """The exact CRS <-> map chain of this mission."""
        return FrameChain(self.crs, self.lla_ref, self.T_map_enu)

    def true_pose(self, stamp: Stamp) -> NDArray[np.float64]:
        """True T_map_base of the node with this stamp (:class:`TruthLookupError` if none)."""
        hit = np.flatnonzero(self.true_poses.stamps_ns == stamp.ns)
        if len(hit) != 1:
            found = "no" if len(hit) == 0 else f"{len(hit)}"
            raise TruthLookupError(
                f"{found} true poses for stamp {stamp}", path=self.path / "true_poses.csv"
            )
        return self.true_poses.poses[int(hit[0])]

    def payload_points(self, stamp: Stamp) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """Original CRS coordinates and source point indices of a scan-derived payload.

        A missing file raises :class:`MissionNotFoundError`, an unreadable one FormatError."""
        folder = self.path / "payload_points"
        arrays = []
        for prefix in ("points", "index"):
            path = folder / stamp.filename(prefix, "npy")
            try:
                arrays.append(np.load(path, allow_pickle=False))
            except OSError as exc:
                raise _open_error(exc, path, "payload truth file") from exc
            except ValueError as exc:
                raise FormatError(f"not a NumPy array file: {exc}", path=path) from exc
        return arrays[0], arrays[1]


def _fmt(v: float, digits: int) -> str:
    return f"{v:.{digits}f}"


def write_trees_csv(trees: Trees, path: Path) -> None:
    """The tree list; the :data:`STAND_COLUMNS` too unless it is a plain plantation."""
    stand = not trees.is_plantation
    with path.open("w", encoding="utf-8", newline="") as fh:
        out = csv.writer(fh, lineterminator="\n")
        out.writerow(TREE_COLUMNS + STAND_COLUMNS if stand else TREE_COLUMNS)
        for k in range(len(trees)):
            row = [
                int(trees.tree_id[k]),
                _fmt(trees.x[k], 4),
                _fmt(trees.y[k], 4),
                _fmt(trees.z_ground[k], 4),
                _fmt(trees.dbh[k], 4),
                _fmt(trees.height[k], 3),
                _fmt(trees.crown_base[k], 3),
                _fmt(trees.crown_radius[k], 3),
                str(trees.species[k]),
                str(trees.status[k]),
            ]
            if stand:
                fork = trees.fork_height_m[k]
                row += [
                    str(trees.kind[k]),
                    _fmt(trees.lean_deg[k], 3),
                    _fmt(trees.lean_azimuth_deg[k], 3),
                    _fmt(fork, 3) if np.isfinite(fork) else "",
                    _fmt(trees.x_bh[k], 4),
                    _fmt(trees.y_bh[k], 4),
                    _fmt(trees.foliage_density[k], 4),
                ]
            out.writerow(row)


def write_shrubs_csv(shrubs: Shrubs, path: Path) -> None:
    with path.open("w", encoding="utf-8", newline="") as fh:
        out = csv.writer(fh, lineterminator="\n")
        out.writerow(SHRUB_COLUMNS)
        for k in range(len(shrubs)):
            out.writerow(
                [
                    _fmt(v, 4)
                    for v in (
                        shrubs.x[k],
                        shrubs.y[k],
                        shrubs.z_ground[k],
                        shrubs.radius[k],
                        shrubs.height[k],
                    )
                ]
            )


def write_gnss_truth(
    stamps_ns: NDArray[np.int64], xyz: NDArray[np.float64], outlier: NDArray[np.bool_], path: Path
) -> None:
    sec, nsec = np.divmod(stamps_ns, 1_000_000_000)
    lines = [GNSS_TRUTH_HEADER]
    for s, n, p, o in zip(sec.tolist(), nsec.tolist(), xyz.tolist(), outlier.tolist(), strict=True):
        lines.append(f"{s},{n},{p[0]!r},{p[1]!r},{p[2]!r},{int(o)}")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def is_truth_folder(path: str | Path) -> bool:
    """True when ``path`` is a simulator truth folder (what simulating with overwrite may
    replace)."""
    return (Path(path) / "truth.json").is_file()


def write_truth_json(info: dict[str, Any], path: Path) -> None:
    path.write_text(json.dumps(info, indent=2, sort_keys=True) + "\n", encoding="utf-8")


def _read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(encoding="utf-8", newline="") as fh:
        return list(csv.DictReader(fh))


def _trees_from_csv(path: Path) -> Trees:
    rows = _read_csv(path)
    try:

        def col(name: str) -> NDArray[np.float64]:
            blank = "nan" if name == "fork_height_m" else ""  # empty fork height: no fork
            return np.array([float(r[name] or blank) for r in rows], dtype=np.float64)

        stand: dict[str, Any] = {}
        if rows and "kind" in rows[0]:  # a mixed stand's columns
            stand["kind"] = np.array([r["kind"] for r in rows], dtype=np.str_)
            stand.update({c: col(c) for c in STAND_COLUMNS[1:]})
        return Trees(
            tree_id=np.array([int(r["tree_id"]) for r in rows], dtype=np.int64),
            x=col("x"),
            y=col("y"),
            z_ground=col("z_ground"),
            dbh=col("dbh_m"),
            height=col("height_m"),
            crown_base=col("crown_base_m"),
            crown_radius=col("crown_radius_m"),
            species=np.array([r["species"] for r in rows], dtype=np.str_),
            status=np.array([r["status"] for r in rows], dtype=np.str_),
            **stand,
        )
    except (KeyError, ValueError) as exc:
        raise FormatError(f"bad tree list: {exc}", path=path) from exc


def _shrubs_from_csv(path: Path) -> Shrubs:
    rows = _read_csv(path)
    try:
        cols = [np.array([float(r[c]) for r in rows], dtype=np.float64) for c in SHRUB_COLUMNS]
    except (KeyError, ValueError) as exc:
        raise FormatError(f"bad shrub list: {exc}", path=path) from exc
    return Shrubs(*cols)


def _gnss_truth_from_csv(
    path: Path,
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.bool_]]:
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, dtype=np.float64)
        ints = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, usecols=(0, 1), dtype=np.int64)
    except OSError as exc:
        raise _open_error(exc, path, "GNSS truth") from exc
    except ValueError as exc:
        raise FormatError(f"bad GNSS truth: {exc}", path=path) from exc
    if len(data) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, bool)
    stamps = ints[:, 0] * 1_000_000_000 + ints[:, 1]
    return stamps, data[:, 2:5].copy(), data[:, 5].astype(bool)


def load_truth(truth_dir: str | Path) -> Truth:
    """Read the truth folder written beside a simulated mission."""
    folder = Path(truth_dir)
    meta_path = folder / "truth.json"
    if not meta_path.is_file():
        raise MissionNotFoundError("no truth.json in truth folder", path=folder)
    try:
        info = json.loads(meta_path.read_text(encoding="utf-8"))
        terrain = Terrain.from_dict(info["terrain"]) if info.get("terrain") else None
        lla_ref = tuple(float(v) for v in info["lla_ref"])
        T = np.asarray(info["T_map_enu"], dtype=np.float64).reshape(4, 4)
        bounds = tuple(float(v) for v in info["bounds"])
        name, crs, seed = str(info["mission"]), str(info["crs"]), int(info["seed"])
        epoch = int(info.get("epoch", 1))
    except KeyError as exc:
        raise FormatError(f"bad truth.json: missing key {exc.args[0]!r}", path=meta_path) from exc
    except (ValueError, TypeError, AttributeError) as exc:
        raise FormatError(f"bad truth.json: {exc}", path=meta_path) from exc
    except OSError as exc:
        raise _open_error(exc, meta_path, "truth.json") from exc
    trees = _trees_from_csv(folder / "trees.csv") if (folder / "trees.csv").is_file() else None
    shrubs = _shrubs_from_csv(folder / "shrubs.csv") if (folder / "shrubs.csv").is_file() else None
    g_stamps, g_xyz, g_out = _gnss_truth_from_csv(folder / "gnss_truth.csv")
    return Truth(
        path=folder,
        name=name,
        kind=str(info.get("kind", "simulated")),
        crs=crs,
        lla_ref=(lla_ref[0], lla_ref[1], lla_ref[2]),
        T_map_enu=T,
        seed=seed,
        epoch=epoch,
        date=str(info.get("date", "")),
        bounds=(bounds[0], bounds[1], bounds[2], bounds[3]),
        terrain=terrain,
        trees=trees,
        shrubs=shrubs,
        true_poses=read_poses_csv(folder / "true_poses.csv"),
        gnss_stamps_ns=g_stamps,
        gnss_true_xyz=g_xyz,
        gnss_outlier=g_out,
        info=info,
    )
