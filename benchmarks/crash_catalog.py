"""Crash harness for the catalog: kill tile, enrich and compare at every commit point and at
random moments, concurrent writers included, and check after each kill that

1. a reader (``Catalog.reading``) sees the old or the new state, and that state is whole:
   catalog.json, the index's missions layer and the points in the tiles agree mission by
   mission, every indexed tile exists, every enriched epoch has its rasters and tables;
2. the next run completes;
3. no point is lost: afterwards every mission holds exactly its points.

Commit points are named by ``$STANDGRID_CRASH_AT`` (``standgrid.catalog.journal.crash_point``):
``staged``, ``journal``, ``rename-<k>``, ``before-catalog-json``, ``applied`` inside a
transaction, ``publish`` and ``exchanged`` when a built catalog replaces another.

Not a test (minutes, not seconds):

    python benchmarks/crash_catalog.py                # the full run (~10 min on 2 cores)
    python benchmarks/crash_catalog.py --random 2 --concurrent 2 --points staged,journal
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import laspy  # noqa: E402
import numpy as np  # noqa: E402
import pyogrio  # noqa: E402

from standgrid.catalog import Catalog  # noqa: E402

BUNDLED = REPO / "data" / "missions"
A_SRC = BUNDLED / "2024-05-14-wytham-anymal-coyote"
B_SRC = BUNDLED / "2028-05-20-wytham-frontier-v15"
CLI = "from standgrid.cli import main; main()"
TXN_POINTS = [
    "staged",
    "journal",
    "rename-0",
    "rename-1",
    "rename-7",
    "rename-20",
    "before-catalog-json",
    "applied",
]
PUBLISH_POINTS = ["publish", "exchanged"]


def small_copy(source: Path, root: Path, name: str | None = None, keep: int = 4) -> Path:
    """A mission with its first ``keep`` payload clouds (and another name when given)."""
    target = root / (name or source.name)
    shutil.copytree(source, target)
    for cloud in sorted((target / "payload_clouds").glob("*.pcd"))[keep:]:
        cloud.unlink()
    if name:
        meta = target / "metadata.yaml"
        meta.write_text(meta.read_text().replace(source.name, name))
    return target


def command(args: list[str], crash_at: str | None = None) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    env.pop("STANDGRID_CRASH_AT", None)
    if crash_at:
        env["STANDGRID_CRASH_AT"] = crash_at
    return subprocess.Popen(
        [sys.executable, "-c", CLI, *args, "-q", "--lock-timeout", "600"],
        env=env,
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def run(args: list[str]) -> None:
    proc = command(args)
    _, err = proc.communicate(timeout=900)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} failed: {err.strip()}")


# --- what a reader sees ------------------------------------------------------------------


def observe(catalog: Path) -> dict[str, Any]:
    """The state a reader sees, checked to be whole; raises AssertionError when it is not."""
    with Catalog.reading(catalog, lock_timeout=600) as snap:
        state = snap._state
        missions = {n: int(r["point_count"]) for n, r in state["missions"].items()}
        layer = pyogrio.read_dataframe(catalog / "index.gpkg", layer="missions")
        assert sorted(layer["mission"]) == sorted(missions), "index missions != catalog.json"
        cells = pyogrio.read_dataframe(catalog / "index.gpkg", layer="cells")
        by_number = {int(r["number"]): n for n, r in state["missions"].items()}
        on_disk = dict.fromkeys(missions, 0)
        for rel in sorted(set(cells["tile_path"])):
            las = laspy.read(catalog / rel)
            core = ~np.asarray(las.withheld, dtype=bool)
            ids, counts = np.unique(np.asarray(las.point_source_id)[core], return_counts=True)
            for number, count in zip(ids, counts, strict=True):
                on_disk[by_number[int(number)]] += int(count)
        assert on_disk == missions, f"points in tiles {on_disk} != catalog.json {missions}"
        listed = {t for n in state["missions"].values() for t in n.get("tiles", [])}
        assert listed == set(cells["tile_path"]), "catalog.json tiles != index cells"
        enriched = {e: bool(v.get("enriched")) for e, v in state["epochs"].items()}
        for epoch, done in enriched.items():
            if done:
                for rel in (f"rasters/{epoch}/chm.tif", f"tables/tree_list_{epoch}.parquet"):
                    assert (catalog / rel).is_file(), f"enriched epoch {epoch} lacks {rel}"
        comparisons = sorted(state.get("comparisons", {}))
        for entry in state.get("comparisons", {}).values():
            for rel in entry["outputs"].values():
                assert (catalog / rel).is_file(), f"comparison output {rel} missing"
    return {"missions": missions, "enriched": enriched, "comparisons": comparisons}


# --- scenarios ---------------------------------------------------------------------------


@dataclass
class Scenario:
    name: str
    base: Path | None  # catalog to start from (copied), None: no catalog
    args: list[str]  # the operation ({cat} = the catalog)
    old: dict[str, Any] | None = None
    new: dict[str, Any] | None = None
    seconds: float = 1.0


def fill(args: list[str], catalog: Path) -> list[str]:
    return [a.replace("{cat}", str(catalog)) for a in args]


def prepare(scenario: Scenario, work: Path) -> Path:
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    catalog = work / "cat"
    if scenario.base is not None:
        shutil.copytree(scenario.base, catalog)
    return catalog


def trial(scenario: Scenario, work: Path, crash_at: str | None, kill_after: float | None) -> str:
    """One killed run and its checks; returns "ok", "no-kill" (finished first) or raises."""
    catalog = prepare(scenario, work)
    proc = command(fill(scenario.args, catalog), crash_at)
    if kill_after is not None:
        try:
            proc.wait(timeout=kill_after)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=900)
    killed = proc.returncode == -signal.SIGKILL
    if proc.returncode not in (0, -signal.SIGKILL):
        raise AssertionError(f"run failed: {proc.stderr.read() if proc.stderr else ''}")
    if (catalog / "catalog.json").is_file():
        seen = observe(catalog)
        assert seen in (scenario.old, scenario.new), f"neither old nor new: {seen}"
    else:
        assert scenario.old is None, "the old catalog is gone"
    run(fill(scenario.args, catalog))  # the next run completes
    assert observe(catalog) == scenario.new, "after the re-run: not the new state"
    leftovers = [p.name for p in work.iterdir() if p.name.endswith(".tmp")]
    assert not leftovers and not (catalog / ".staging").exists(), f"left over: {leftovers}"
    return "ok" if killed else "no-kill"


def concurrent_trial(
    base: Path,
    work: Path,
    b: Path,
    c: Path,
    rng: random.Random,
    crash_at: str | None,
    seconds: float,
) -> str:
    """Two writers add B and C at once; one is killed (at a point or at random)."""
    catalog = prepare(Scenario("", base, []), work)
    first = rng.random() < 0.5
    victim_mission, survivor_mission = (b, c) if first else (c, b)
    victim = command(["tile", str(victim_mission), "-o", str(catalog)], crash_at)
    survivor = command(["tile", str(survivor_mission), "-o", str(catalog)])
    if crash_at is None:
        try:
            victim.wait(timeout=rng.uniform(0.2, 2.0) * seconds)
        except subprocess.TimeoutExpired:
            victim.send_signal(signal.SIGKILL)
    victim.wait(timeout=900)
    survivor.wait(timeout=900)
    assert survivor.returncode == 0, survivor.stderr.read() if survivor.stderr else ""
    seen = observe(catalog)
    assert survivor_mission.name in seen["missions"], "the surviving writer's mission is lost"
    run(["tile", str(victim_mission), "-o", str(catalog)])
    final = observe(catalog)
    assert sorted(final["missions"]) == sorted([A_SRC.name, b.name, c.name]), (
        f"missions after the re-run: {sorted(final['missions'])}"
    )
    return "ok" if victim.returncode == -signal.SIGKILL else "no-kill"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--random", type=int, default=6, help="random kills per scenario")
    parser.add_argument("--concurrent", type=int, default=10, help="concurrent-writer trials")
    parser.add_argument("--points", default=",".join(TXN_POINTS), help="commit points to kill at")
    parser.add_argument("--seed", type=int, default=8)
    parser.add_argument("--only", default="", help="comma-separated scenario name parts")
    parser.add_argument("--keep", action="store_true", help="keep the work folder")
    opts = parser.parse_args()
    rng = random.Random(opts.seed)
    points = [p for p in opts.points.split(",") if p]
    root = Path(tempfile.mkdtemp(prefix="standgrid-crash-"))
    started = time.monotonic()
    try:
        missions = root / "missions"
        a = small_copy(A_SRC, missions)
        b = small_copy(B_SRC, missions)
        c = small_copy(A_SRC, missions, name="2024-05-16-wytham-anymal-coyote", keep=3)
        bases = root / "bases"
        bases.mkdir()
        # reference states, each made by clean runs (also timing the operations)
        cat_a = bases / "a"
        run(["tile", str(a), "-o", str(cat_a)])
        cat_ab = bases / "ab"
        shutil.copytree(cat_a, cat_ab)
        t0 = time.monotonic()
        run(["tile", str(b), "-o", str(cat_ab)])
        t_tile = time.monotonic() - t0
        cat_abe = bases / "abe"
        shutil.copytree(cat_ab, cat_abe)
        t0 = time.monotonic()
        run(["enrich", str(cat_abe)])
        t_enrich = time.monotonic() - t0
        cat_abec = bases / "abec"
        shutil.copytree(cat_abe, cat_abec)
        t0 = time.monotonic()
        run(["compare", str(cat_abec)])
        t_compare = time.monotonic() - t0
        cat_b = bases / "b"
        run(["tile", str(b), "-o", str(cat_b)])
        cat_ac = bases / "ac"
        shutil.copytree(cat_a, cat_ac)
        run(["tile", str(c), "-o", str(cat_ac)])
        scenarios = [
            Scenario(
                "tile (new epoch)",
                cat_a,
                ["tile", str(b), "-o", "{cat}"],
                observe(cat_a),
                observe(cat_ab),
                t_tile,
            ),
            Scenario(
                "tile (merge into an epoch)",
                cat_a,
                ["tile", str(c), "-o", "{cat}"],
                observe(cat_a),
                observe(cat_ac),
                t_tile,
            ),
            Scenario(
                "tile --overwrite",
                cat_a,
                ["tile", str(b), "-o", "{cat}", "--overwrite"],
                observe(cat_a),
                observe(cat_b),
                t_tile,
            ),
            Scenario(
                "tile (new catalog)",
                None,
                ["tile", str(a), "-o", "{cat}"],
                None,
                observe(cat_a),
                t_tile,
            ),
            Scenario(
                "enrich", cat_ab, ["enrich", "{cat}"], observe(cat_ab), observe(cat_abe), t_enrich
            ),
            Scenario(
                "compare",
                cat_abe,
                ["compare", "{cat}"],
                observe(cat_abe),
                observe(cat_abec),
                t_compare,
            ),
        ]
        print(
            f"setup {time.monotonic() - started:.0f} s; tile {t_tile:.1f} s, enrich "
            f"{t_enrich:.1f} s, compare {t_compare:.1f} s per run",
            flush=True,
        )
        tally: Counter[str] = Counter()
        failures: list[str] = []
        work = root / "work"

        def record(label: str, fn: Any) -> None:
            try:
                outcome = fn()
            except Exception as exc:  # a failed check: report and go on
                outcome = "FAIL"
                failures.append(f"{label}: {type(exc).__name__}: {exc}")
            tally[outcome] += 1
            print(f"  {outcome:7s} {label}", flush=True)

        wanted = [w for w in opts.only.split(",") if w]
        for scenario in scenarios:
            if wanted and not any(w in scenario.name for w in wanted):
                continue
            print(f"{scenario.name}:", flush=True)
            extra = (
                PUBLISH_POINTS if scenario.base is None or "--overwrite" in scenario.args else []
            )
            for point in [*points, *extra]:
                record(
                    f"{scenario.name} @ {point}",
                    lambda s=scenario, p=point: trial(s, work, p, None),
                )
            for _ in range(opts.random):
                after = rng.uniform(0.1, 1.1) * scenario.seconds
                record(
                    f"{scenario.name} @ {after:.2f} s",
                    lambda s=scenario, t=after: trial(s, work, None, t),
                )
        print("concurrent writers (tile B and tile C into one catalog, one killed):", flush=True)
        for k in range(opts.concurrent):
            point = rng.choice(points) if k % 2 else None
            record(
                f"concurrent @ {point or 'random'}",
                lambda p=point: concurrent_trial(cat_a, work, b, c, rng, p, t_tile),
            )
        total = sum(tally.values())
        summary = {
            "trials": total,
            "killed_and_checked": tally["ok"],
            "finished_before_the_kill_and_checked": tally["no-kill"],
            "failures": tally["FAIL"],
            "minutes": round((time.monotonic() - started) / 60, 1),
        }
        print(json.dumps(summary))
        for failure in failures:
            print("FAILURE", failure)
    finally:
        if not opts.keep:
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
