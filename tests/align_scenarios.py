"""Missions under a canopy with GNSS as it is there (issue 20's acceptance): a mixed stand
scanned from below by two robots on one day and again four years later, each mission's
GNSS biased, walking and stating 0.5 m; the real pipeline tiles them, and every figure is
measured against the simulator's truth.

``python -m tests.align_scenarios OUT SEED`` simulates one campaign set and prints its
placement figures with and without alignment."""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

AREA_M = 60.0
POINTS_PER_PAYLOAD = 120_000
#: epochs of the simulator: 1 (robot A, 2024), 3 (robot B, same day), 2 (2028)
EPOCHS = (1, 3, 2)


def simulate(
    root: Path,
    seed: int,
    *,
    harvest: float = 0.0,
    exact: bool = False,
    epochs: tuple[int, ...] = EPOCHS,
) -> list[Any]:
    """The missions under ``root/missions`` and their truth; ``exact``: the pose graphs also
    carry the true georeference (placement exact, the same data otherwise)."""
    from standgrid.simulate import simulate_mission
    from standgrid.simulate.gnss import GnssModel

    settings = dict(
        area=AREA_M,
        forest="mixed",
        scanner_kind="handheld",
        lane_spacing=15.0,
        points_per_payload=POINTS_PER_PAYLOAD,
        gnss=GnssModel.under_canopy(),
        harvest_fraction=harvest,
        new_trees=3 if harvest > 0 else 0,
        write_georef=exact,
    )
    return [simulate_mission(root, seed=seed, epoch=e, overwrite=True, **settings) for e in epochs]


@dataclass(frozen=True)
class Placements:
    """Per mission: nodes' true CRS positions and where the catalog put them, its stated
    DRMS 1-sigma; per pair: how far apart the two put the same ground."""

    error: dict[str, np.ndarray]
    sigma_h: dict[str, float | None]
    apart: dict[tuple[str, str], np.ndarray]
    #: per mission, the rigid 2-D motion (rotation, then shift) taking true positions to
    #: where the catalog put them, fitted over its nodes
    motion: dict[str, tuple[np.ndarray, np.ndarray]]

    def placed(self, name: str, xy: np.ndarray) -> np.ndarray:
        """True positions ``xy`` (n, 2) where the catalog put mission ``name``'s ground."""
        rot, shift = self.motion[name]
        return np.asarray(xy, dtype=np.float64) @ rot.T + shift

    def coverage(self, name: str, k: float = 2.0) -> float:
        sigma = self.sigma_h[name]
        return math.nan if sigma is None else float(np.mean(self.error[name] <= k * sigma))

    def report(self) -> str:
        lines = []
        for name, err in self.error.items():
            lines.append(
                f"{name}: error median {np.median(err):.3f} m, max {err.max():.3f} m; stated "
                f"1-sigma {self.sigma_h[name]}; within 1 / 2 sigma {self.coverage(name, 1):.2f}"
                f" / {self.coverage(name):.2f}"
            )
        for (a, b), d in self.apart.items():
            lines.append(
                f"{a} ~ {b}: {len(d)} co-located nodes, apart median "
                f"{np.median(d):.4f} m, max {d.max():.4f} m"
            )
        return "\n".join(lines)


def placements(root: Path, catalog: Path) -> Placements:
    """Where ``catalog`` placed each simulated mission of ``root``, against the truth."""
    from scipy.spatial import cKDTree

    from standgrid.georeference.fit import GeoreferenceFit
    from standgrid.georeference.project import MapProjector
    from standgrid.mission.opening import open_mission
    from standgrid.simulate import load_truth

    state = json.loads((catalog / "catalog.json").read_text())
    crs = state["crs"]
    projector, chain, true_nodes, sigma = {}, {}, {}, {}
    error, motion = {}, {}
    for name, record in sorted(state["missions"].items()):
        geo = record["georeference"]
        fit = GeoreferenceFit.without_fixes(
            tuple(geo["lla_ref"]), np.array(geo["T_enu_map"]), geo["method"]
        )
        projector[name] = MapProjector(fit, crs)
        chain[name] = load_truth(root / "truth" / name).chain()
        nodes = open_mission(root / "missions" / name).trajectory()[1]
        true_nodes[name] = chain[name].map_to_crs(nodes)
        placed = projector[name].exact(nodes)
        error[name] = np.hypot(*(placed - true_nodes[name])[:, :2].T)
        motion[name] = _rigid(true_nodes[name][:, :2], placed[:, :2])
        sigma[name] = (geo.get("alignment") or {}).get("sigma_h_m")
    apart = {}
    names = sorted(error)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            d, _ = cKDTree(true_nodes[b][:, :2]).query(true_nodes[a][:, :2])
            ground = true_nodes[a][d < 3.0]
            if not len(ground):
                continue
            pa = projector[a].exact(chain[a].crs_to_map(ground))
            pb = projector[b].exact(chain[b].crs_to_map(ground))
            apart[(a, b)] = np.hypot(*(pa - pb)[:, :2].T)
    return Placements(error, sigma, apart, motion)


def _rigid(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and shift taking ``a`` onto ``b`` (2-D Procrustes)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, v = a - ca, b - cb
    yaw = math.atan2(
        float(np.sum(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])),
        float(np.sum(u[:, 0] * v[:, 0] + u[:, 1] * v[:, 1])),
    )
    rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    return rot, cb - rot @ ca


def main(out: Path, seed: int) -> None:
    from standgrid.pipeline.tile import tile_missions
    from standgrid.tiling.options import TileOptions

    simulate(out, seed)
    missions = sorted((out / "missions").iterdir())
    for align in (False, True):
        catalog = out / f"catalog_{'aligned' if align else 'gnss'}"
        tile_missions(missions, catalog, TileOptions(overwrite=True, align=align))
        print(f"--- {'aligned' if align else 'GNSS only'}")
        print(placements(out, catalog).report())


if __name__ == "__main__":
    main(Path(sys.argv[1]), int(sys.argv[2]))
