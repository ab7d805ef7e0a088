"""A writer waiting for the catalog's readers (a :meth:`Catalog.reading` block held open in
another process or thread) says so on stderr after about a second, and gives up at
``--lock-timeout`` with a :class:`CatalogBusyError` naming the catalog and the reader."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from click.testing import CliRunner

from standgrid.catalog import Catalog
from standgrid.cli import cli
from standgrid.errors import CatalogBusyError
from standgrid.pipeline.tile import tile_missions
from standgrid.tiling.options import TileOptions
from tests.conftest import BUNDLED_MISSIONS, REPO_ROOT
from tests.pipeline_fixtures import MISSIONS

HOLD = """
import sys, time
from standgrid.catalog import Catalog
with Catalog.reading(sys.argv[1]):
    print("held", flush=True)
    time.sleep(120)
"""


@pytest.fixture(scope="module")
def tiled(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One bundled mission tiled (not enriched): the catalog the tests lock."""
    folder = tmp_path_factory.mktemp("lockwait") / "c24"
    tile_missions([BUNDLED_MISSIONS / MISSIONS["2024"]], folder, TileOptions())
    return folder


@pytest.fixture
def reader_process(tiled: Path) -> Iterator[subprocess.Popen[str]]:
    """Another process inside ``Catalog.reading(tiled)`` until the test ends."""
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(tiled)],
        cwd=REPO_ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    yield proc
    proc.kill()
    proc.wait(timeout=30)


@pytest.mark.parametrize(
    "args",
    [
        ["enrich", "{c}"],
        ["compare", "{c}", "--other", "{c}_other"],
        ["tile", str(BUNDLED_MISSIONS / MISSIONS["2024"]), "-o", "{c}"],
    ],
    ids=["enrich", "compare", "tile"],
)
def test_a_writer_gives_up_waiting_for_a_reader_at_lock_timeout(
    tiled: Path, reader_process: subprocess.Popen[str], args: list[str]
) -> None:
    other = tiled.parent / f"{tiled.name}_other"
    other.mkdir(exist_ok=True)
    before = (tiled / "catalog.json").read_bytes()
    words = [a.format(c=tiled) for a in args] + ["--lock-timeout", "1"]
    start = time.monotonic()
    result = CliRunner().invoke(cli, words)
    waited = time.monotonic() - start
    assert result.exit_code == 1, result.output
    assert "Error: CatalogBusyError: " in result.output
    assert f"{tiled}: another process is reading this catalog" in result.output
    assert f"held by pid {reader_process.pid}:" in result.output  # who, and its command
    assert waited < 20  # not the 30 s default, not for ever (it hung before)
    assert (tiled / "catalog.json").read_bytes() == before
    assert reader_process.poll() is None  # the reader was not disturbed


def test_a_writer_says_it_waits_for_readers_and_goes_on_when_they_leave(tiled: Path) -> None:
    held = threading.Event()

    def read_for_a_while() -> None:
        with Catalog.reading(tiled):
            held.set()
            time.sleep(2.5)

    reader = threading.Thread(target=read_for_a_while)
    reader.start()
    try:
        assert held.wait(30)
        result = CliRunner().invoke(cli, ["enrich", str(tiled), "-q", "--lock-timeout", "60"])
    finally:
        reader.join()
    assert result.exit_code == 0, result.output
    lines = [x for x in result.stderr.splitlines() if "waiting for readers" in x]
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith(f"{tiled}: waiting for readers to finish (pid ")
    assert "this process" in lines[0] and lines[0].endswith("up to 60 s")
    assert Catalog.open(tiled).epoch("2024").enriched


class _Reader(threading.Thread):
    """``Catalog.reading`` held in a thread from :meth:`start` until :meth:`stop`."""

    def __init__(self, catalog: Path) -> None:
        super().__init__()
        self.catalog = catalog
        self.held = threading.Event()
        self.release = threading.Event()

    def run(self) -> None:
        with Catalog.reading(self.catalog):
            self.held.set()
            self.release.wait(60)

    def __enter__(self) -> _Reader:
        self.start()
        assert self.held.wait(30)
        return self

    def __exit__(self, *exc: object) -> None:
        self.release.set()
        self.join()


def test_a_transaction_waits_for_readers_only_up_to_the_lock_timeout(tiled: Path) -> None:
    """Starting a transaction (it finishes dead commits first) and committing one (journal
    and renames) wait for readers up to the timeout; then the staged work is discarded and
    the catalog left as it was."""
    before = (tiled / "catalog.json").read_bytes()
    with Catalog.writing(tiled, lock_timeout=0.5) as catalog:
        with _Reader(tiled), pytest.raises(CatalogBusyError, match=r"pid [0-9]+: this process"):
            catalog.transaction().__enter__()  # was OutputNotWritableError
        with (
            pytest.raises(CatalogBusyError, match="reading this catalog"),
            catalog.transaction() as txn,
        ):
            txn.stage("tables/note.txt").write_text("staged")
            reader = _Reader(tiled).__enter__()  # a reader comes in while it stages
        reader.__exit__()
    assert (tiled / "catalog.json").read_bytes() == before
    assert not (tiled / "tables" / "note.txt").exists()
    assert not (tiled / ".staging").exists()
