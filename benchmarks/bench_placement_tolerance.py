"""Streaming a GNSS-fit mission into a catalog with and without the placement tolerance.

A robot sends its mission batch by batch (the pose graph so far, ``--batch`` payloads with
their node poses, the GNSS fixes so far) and asks for a tile after each batch, as
``standgrid serve`` does it (:func:`standgrid.serve.workers.tile_mission`, called in this
process: the same code the server's tiling worker runs). Every batch refits the
georeference; without a tolerance each refit re-tiles the whole epoch (O(N^2) over the
mission), with one (default 0.05 m, the server's) the epoch re-tiles in place while the refit
moves the mission less than that, and an exact settle (``tile?exact=true``) ends the stream.
It prints the tiling time of both streams, how many tiles were whole re-tiles, their ratio,
and checks the two final catalogs are the same, tile for tile, point for point.

Example (a simulated 86-payload, 5.1 M-point mission with GNSS fixes):
    standgrid simulate /tmp/sim --epochs 1 --area 200 --points-per-payload 60000 --seed 3
    python benchmarks/bench_placement_tolerance.py --mission /tmp/sim/missions/2024-*
    python benchmarks/bench_placement_tolerance.py               # the bundled 2024 mission
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BUNDLED = REPO / "data" / "missions" / "2024-05-14-wytham-anymal-coyote"


def stream(source: Path, folder: Path, batch: int, tolerance: float | None) -> dict[str, Any]:
    """Stream ``source`` into a new catalog in ``folder``; tiling times and placements."""
    from standgrid.catalog import Catalog
    from standgrid.errors import GeoreferenceError
    from standgrid.mission.live import LiveMission
    from standgrid.mission.metadata import read_metadata
    from standgrid.mission.opening import open_mission
    from standgrid.partition import StandGrid
    from standgrid.serve.workers import tile_mission
    from standgrid.simulate.stream import fixes_until, graph_until

    mission = open_mission(source, strict=False)
    crs = "EPSG:32630"  # the simulator's (Wytham Woods)
    catalog = folder / "catalog"
    Catalog.create(catalog, StandGrid(crs, 20.0).to_dict(), crs, "grid")
    (folder / "missions").mkdir()
    live = LiveMission(folder / "missions" / source.name)
    live.create(read_metadata(source / "metadata.yaml"))
    payloads = mission.payloads
    result: dict[str, Any] = {"tiling_s": 0.0, "tiles": 0, "whole": 0, "kept": 0, "offsets": []}
    for start in range(0, len(payloads), batch):
        chunk = payloads[start : start + batch]
        until = payloads[start + batch].stamp.ns - 1 if start + batch < len(payloads) else 1 << 62
        live.set_graph(graph_until(source, until))
        for payload in chunk:
            live.add_payload(
                payload.stamp,
                payload.path.read_bytes(),
                payload.path.suffix,
                mission.pose_of(payload),
            )
        live.add_gnss(fixes_until(source, until))
        t0 = time.perf_counter()
        try:
            report = tile_mission(str(live.path), str(catalog), tolerance)
        except GeoreferenceError as exc:  # too few fixes yet: the robot asks again later
            print(f"  batch at payload {start}: {exc.message[:80]}", file=sys.stderr)
            continue
        result["tiling_s"] += time.perf_counter() - t0
        _count(result, report, source.name)
    if tolerance is not None:  # the end of the mission: settle on the fresh fit
        t0 = time.perf_counter()
        report = tile_mission(str(live.path), str(catalog), None)
        result["settle_s"] = time.perf_counter() - t0
        result["tiling_s"] += result["settle_s"]
        _count(result, report, source.name)
    result["catalog"] = catalog
    return result


def _count(result: dict[str, Any], report: dict[str, Any], name: str) -> None:
    epoch = next(iter(report["epochs"].values()))
    placement = report["missions"][name]["placement"]
    result["tiles"] += 1
    result["whole"] += epoch["cells_rewritten"] == epoch["cells"]
    if placement["used"] == "kept":
        result["kept"] += 1
        result["offsets"].append(placement["offset_m"])


def same_catalogs(a: Path, b: Path) -> None:
    """The two catalogs hold the same tiles with the same points (raises otherwise)."""
    from standgrid.catalog import Catalog
    from standgrid.export.las import read_tile

    def points(path: Path) -> np.ndarray:
        cloud = read_tile(path, include_withheld=True)
        table = np.column_stack(
            [
                np.round(cloud.xyz * 1000).astype(np.int64),
                cloud.fields["payload_id"].astype(np.int64),
            ]
        )
        return table[np.lexsort(table.T[::-1])]

    ca, cb = Catalog.open(a), Catalog.open(b)
    tiles_a = sorted(t for e in ca.epochs for t in ca.tiles(e))
    tiles_b = sorted(t for e in cb.epochs for t in cb.tiles(e))
    if tiles_a != tiles_b:
        raise SystemExit(f"different tiles: {len(tiles_a)} vs {len(tiles_b)}")
    for rel in tiles_a:
        if not np.array_equal(points(ca.path(rel)), points(cb.path(rel))):
            raise SystemExit(f"tile {rel} differs")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mission", type=Path, default=BUNDLED, help="a mission folder")
    parser.add_argument("--batch", type=int, default=1, help="payloads per tile request")
    parser.add_argument("--tolerance", type=float, default=0.05, help="metres")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-placement-") as tmp:
        runs = {}
        for label, tolerance in (("exact", None), ("tolerance", args.tolerance)):
            folder = Path(tmp) / label
            folder.mkdir()
            print(f"streaming {args.mission.name} ({label}) ...", file=sys.stderr)
            runs[label] = stream(args.mission, folder, args.batch, tolerance)
        same_catalogs(runs["exact"]["catalog"], runs["tolerance"]["catalog"])
        for label, run in runs.items():
            offsets = run["offsets"]
            extra = (
                (
                    f", {run['kept']} kept the placement (offset <= {max(offsets):.3f} m), "
                    f"exact settle {run['settle_s']:.2f} s"
                )
                if offsets
                else ""
            )
            print(
                f"{label:9}: {run['tiles']} tiles in {run['tiling_s']:7.2f} s, "
                f"{run['whole']} whole re-tiles{extra}"
            )
        ratio = runs["exact"]["tiling_s"] / runs["tolerance"]["tiling_s"]
        print(
            f"exact / tolerance {args.tolerance} m: {ratio:.2f}x; the final catalogs are "
            "the same, tile for tile, point for point"
        )
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
