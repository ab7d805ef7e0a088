"""A finished mission folder as its robot had it at a moment: what a robot streaming the
mission would have sent by then (its pose graph so far, its GNSS log so far). Tests and
benchmarks replay real and simulated folders through online ingest with it."""

from __future__ import annotations

from pathlib import Path

from standgrid.mission.live import GNSS_FILE
from standgrid.mission.writer import GRAPH_FILE


def graph_until(folder: Path, until_ns: int) -> bytes:
    """The folder's pose graph (g2o text) with the nodes stamped up to ``until_ns`` and the
    edges between them."""
    kept: set[str] = set()
    out = []
    for line in (folder / GRAPH_FILE).read_text().splitlines():
        parts = line.split()
        if parts and parts[0].startswith("VERTEX"):
            if int(parts[-2]) * 1_000_000_000 + int(parts[-1]) > until_ns:
                continue
            kept.add(parts[1])
        elif parts and parts[0].startswith("EDGE") and not {parts[1], parts[2]} <= kept:
            continue
        out.append(line)
    return ("\n".join(out) + "\n").encode()


def fixes_until(folder: Path, until_ns: int | None) -> bytes:
    """The folder's GNSS log (text, with its header) up to ``until_ns`` (None: all of it)."""
    header, *rows = (folder / GNSS_FILE).read_text().splitlines()
    if until_ns is not None:
        rows = [r for r in rows if int(r.split(",")[0]) * 10**9 + int(r.split(",")[1]) <= until_ns]
    return ("\n".join([header, *rows]) + "\n").encode()
