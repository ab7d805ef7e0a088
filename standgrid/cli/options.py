"""Options and output helpers shared by every subcommand (defined once, here)."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import click

T = TypeVar("T")
F = TypeVar("F", bound=Callable[..., Any])

json_option = click.option(
    "--json", "as_json", is_flag=True, help="Print machine-readable JSON on stdout."
)
overwrite_option = click.option(
    "--overwrite", is_flag=True, help="Replace outputs that already exist."
)
lock_timeout_option = click.option(
    "--lock-timeout",
    type=click.FloatRange(min=0),
    default=30.0,
    show_default=True,
    help="Seconds to wait while another process writes (or reads) the catalog, then fail cleanly.",
)
quiet_option = click.option("-q", "--quiet", is_flag=True, help="No progress output on stderr.")


def _default_memory_mb() -> int:
    from standgrid.engine.budget import DEFAULT_MEMORY_BUDGET

    return DEFAULT_MEMORY_BUDGET >> 20


memory_option = click.option(
    "--memory",
    "memory_mb",
    type=click.IntRange(min=16),
    default=_default_memory_mb,
    show_default="a quarter of the available RAM, 256 to 4096 MB",
    help="Memory budget in MB of this process (and of each dask worker): chunks are sized, "
    "reads and writes ahead limited, and the partition engine spills to disk by it. The "
    "peak stays within about 1.1x the budget plus the interpreter's own (measured at 512 on "
    "20 M points: tile 548 MB, enrich 792 MB, the interpreter 205-308 MB).",
)


def cluster_options(command: F) -> F:
    """``--workers N`` (a local dask cluster) and ``--scheduler ADDRESS`` (an existing one)."""
    command = click.option(
        "--scheduler",
        metavar="ADDRESS",
        help="Run on an existing dask.distributed cluster (tcp://host:port); every worker must "
        "reach the catalog folder at the same path. The catalog is written only from here.",
    )(command)
    return click.option(
        "--workers",
        type=click.IntRange(min=1),
        help="Run on a local dask cluster of N worker processes (default: this process).",
    )(command)


def mission_argument(nargs: int = 1, scans: bool = False) -> Callable[[F], F]:
    """A mission folder argument (one, or several with ``nargs=-1``); ``scans``: plain scan
    files (LAS/LAZ/COPC, VPC) are taken too."""
    return click.argument(
        "missions" if nargs != 1 else "mission",
        nargs=nargs,
        required=True,
        type=click.Path(exists=True, file_okay=scans, path_type=Path),
    )


def scan_options(command: F) -> F:
    """``--date`` and ``--trajectory``: for plain scans (LAS/LAZ/COPC files, folders, VPCs)."""

    def _date(ctx: click.Context, param: click.Parameter, value: str | None) -> Any:
        import datetime as dt

        if value is None:
            return None
        try:
            return dt.date.fromisoformat(value)
        except ValueError:
            raise click.BadParameter(f"a date YYYY-MM-DD: {value!r}") from None

    command = click.option(
        "--trajectory", type=click.Path(exists=True, dir_okay=False, path_type=Path),
        default=None,
        help="A plain scan's trajectory (time, x, y, z CSV/TXT in the scan's CRS and GPS time"
        " base, as SLAM scanners export it): payloads follow it (~20 m of travel each), for"
        " footprints and Voronoi cells.",
    )(command)  # fmt: skip
    return click.option(
        "--date", "scan_date", default=None, callback=_date, metavar="YYYY-MM-DD",
        help="A plain scan's date (default: its GPS time when adjusted standard, else the"
        " header's creation date); the epoch is its year.",
    )(command)  # fmt: skip


def output_option(required: bool = True, help: str = "Output folder.") -> Callable[[F], F]:
    return click.option(
        "-o", "--output", required=required, type=click.Path(path_type=Path), help=help
    )


def _default(o: object) -> object:
    """JSON encoding for numpy scalars/arrays, paths, dates and dataclass-likes."""
    import dataclasses
    import datetime as dt

    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, dt.date | dt.datetime | dt.time):
        return o.isoformat()
    if dataclasses.is_dataclass(o) and not isinstance(o, type):
        return dataclasses.asdict(o)
    if isinstance(o, set | frozenset | tuple):
        return list(o)
    return str(o)


def emit(data: object, as_json: bool, human: Callable[[Any], str] | None = None) -> None:
    """Data on stdout: JSON for machines, or ``human(data)`` text."""
    if as_json or human is None:
        click.echo(json.dumps(data, indent=2, default=_default))
    else:
        click.echo(human(data))


def progress(
    items: Iterable[T], *, total: int | None = None, desc: str = "", quiet: bool = False
) -> Iterator[T]:
    """A tqdm progress bar on stderr (silent when ``quiet`` or stderr is not a terminal)."""
    from tqdm import tqdm

    disable = quiet or not sys.stderr.isatty()
    yield from tqdm(items, total=total, desc=desc, disable=disable, file=sys.stderr, leave=False)


class TerminalProgress:
    """The CLI's rendering of :class:`standgrid.engine.Progress`: bars and lines on stderr."""

    def __init__(self, quiet: bool = False) -> None:
        self.quiet = quiet

    def track(self, items: Iterable[T], total: int, desc: str) -> Iterable[T]:
        return progress(items, total=total or None, desc=desc, quiet=self.quiet)

    def status(self, message: str) -> None:
        status(message, self.quiet)


def status(message: str, quiet: bool = False) -> None:
    """A progress line on stderr."""
    if not quiet:
        click.echo(message, err=True)


#: ``tile`` and ``run``: a mission of a name the catalog holds, from another folder.
no_align_option = click.option(
    "--no-align", "no_align", is_flag=True,
    help="Place each mission by its own GNSS fit alone (default: missions given together"
    " that overlap are registered to each other on their stems and ground, and placed by one"
    " graph with their GNSS).",
)  # fmt: skip

replace_option = click.option(
    "--replace", "replace_missions", is_flag=True,
    help="A mission whose name the catalog holds, tiled from another folder, replaces it"
    " (else refused). Re-tiling a mission from its own folder needs no --replace.",
)  # fmt: skip
