"""Every option of the commands, declared once (:data:`REGISTRY`), and the output helpers.

An :class:`Option` is one flag with one help text and the library field it sets (a field of
an options class, or of :class:`~standgrid.engine.execution.Execution`), by the field's
name; a command takes the options of its stages (``run``: tiling's, enrichment's and
comparison's) and builds the library's values from them (:func:`build`). The library names
options by their field (``option accept_poor_georeference``); :func:`say_flags` alone turns
those names into flags.
"""

from __future__ import annotations

import json
import re
import sys
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import click

T = TypeVar("T")
F = TypeVar("F", bound=Callable[..., Any])

json_option = click.option(
    "--json", "as_json", is_flag=True, help="Print machine-readable JSON on stdout."
)
quiet_option = click.option("-q", "--quiet", is_flag=True, help="No progress output on stderr.")


class Option(NamedTuple):
    """One option: its flag (``decls``, click's), its click settings (``attrs``: one help
    text), and the fields it sets, ``"Class.field"`` (``convert(value, params)``: the field's
    value from the flag's, and the command's other parameters)."""

    name: str
    decls: tuple[str, ...]
    fields: tuple[str, ...]
    attrs: Mapping[str, Any] = {}
    convert: Callable[[Any, Mapping[str, Any]], Any] | None = None

    def __call__(self, command: F) -> F:
        decorate: Callable[[F], F] = click.option(*self.decls, self.name, **self.attrs)
        return decorate(command)

    @property
    def flag(self) -> str:
        """How the flag is written: ``--grid``; ``--las`` of ``--las/--laz``."""
        return self.decls[0].split("/")[0]

    @property
    def usage(self) -> str:
        """The flag with its metavar: ``--anchor LAT LON ALT YAW``."""
        metavar = self.attrs.get("metavar")
        return f"{self.flag} {metavar}" if metavar else self.flag


def _levels(ctx: click.Context, param: click.Parameter, value: str | None) -> tuple[float, ...]:
    if not value:
        return ()
    try:
        return tuple(float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"cell sizes in metres, comma separated: {value!r}") from None


def _date(ctx: click.Context, param: click.Parameter, value: str | None) -> Any:
    import datetime as dt

    if value is None:
        return None
    try:
        return dt.date.fromisoformat(value)
    except ValueError:
        raise click.BadParameter(f"a date YYYY-MM-DD: {value!r}") from None


def _default_memory_mb() -> int:
    from standgrid.engine.budget import DEFAULT_MEMORY_BUDGET

    return DEFAULT_MEMORY_BUDGET >> 20


def _default_lock_timeout() -> float:
    from standgrid.engine.execution import DEFAULT_LOCK_TIMEOUT

    return DEFAULT_LOCK_TIMEOUT


class Location(click.ParamType):
    """A folder or file (checked as ``path`` checks it), or an object-storage URL
    (``s3://bucket/prefix``, …) taken as it is."""

    name = "path|url"

    def __init__(self, path: click.Path) -> None:
        self.path = path

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        from standgrid.storage import is_url

        if is_url(value):
            return str(value).rstrip("/")
        return self.path.convert(value, param, ctx)


_TILE, _ENRICH, _COMPARE, _RUN = "TileOptions", "EnrichOptions", "CompareOptions", "Execution"

#: Every option of ``tile``, ``align``, ``enrich``, ``compare`` and ``run``, by its name (the
#: library field's, where it sets one).
# fmt: off
REGISTRY: dict[str, Option] = {
    o.name: o
    for o in (
        # tiling
        Option("cell_size", ("--grid",), (f"{_TILE}.cell_size",), {"type": float, "default": None,
               "help": "Stand-grid cell size in metres (default 20; an existing catalog keeps its"
               " own)."}),
        Option("levels", ("--levels",), (f"{_TILE}.levels",), {"default": None,
               "callback": _levels, "help": "Nested cell sizes, finest first, comma separated"
               " (default: SIZE,5*SIZE)."}),
        Option("voronoi", ("--voronoi",), (f"{_TILE}.scheme",),
               {"is_flag": True, "help": "Voronoi cells around payload poses, not a grid."},
               lambda v, p: "voronoi" if v else ("grid" if p.get("cell_size") is not None
                                                  else None)),
        Option("crs", ("--crs",), (f"{_TILE}.crs",), {"default": "auto", "show_default": True,
               "help": "Output CRS: EPSG:XXXX, WKT2, or auto (a new catalog: the missions' UTM"
               " zone, or clouds already projected their own CRS; an existing catalog: its CRS,"
               " refused for a mission outside its area of use). Also the CRS of PCD/PLY clouds"
               " in payload_clouds_in_utm/ and of plain scans, which name none."}),
        Option("anchor", ("--anchor",), (f"{_TILE}.anchor",), {"type": float, "nargs": 4,
               "default": None, "metavar": "LAT LON ALT YAW",
               "help": "Place a mission without GNSS: map origin at WGS 84 LAT LON (deg) and"
               " ellipsoidal ALT (m), map x axis YAW deg counter-clockwise from East (90 -"
               " compass heading)."}),
        Option("buffer", ("--buffer",), (f"{_TILE}.buffer",), {"type": float, "default": None,
               "help": "Copy neighbours' points within this many metres into each tile, flagged"
               " withheld (default 0; an existing catalog keeps its own)."}),
        Option("las", ("--las/--laz",), (f"{_TILE}.laz",), {"default": None,
               "help": "Uncompressed LAS or LAZ tiles (default LAZ; an existing catalog keeps"
               " its own)."}, lambda v, p: None if v is None else not v),
        Option("copc", ("--copc/--no-copc",), (f"{_TILE}.copc",), {"default": None,
               "help": "COPC tiles (*.copc.laz: LAZ that QGIS 3.26+, PDAL and web viewers stream"
               " by range requests; tiling takes 1.1-1.4x the CPU of LAZ). Default: not COPC; an"
               " existing catalog keeps its own."}),
        Option("method", ("--method",), (f"{_TILE}.method",),
               {"type": click.Choice(["yaw2d", "rigid3d"]), "default": "yaw2d",
                "show_default": True,
                "help": "Georeference fit: rotation about z only, or full 3-D."}),
        Option("epoch", ("--epoch",), (f"{_TILE}.epoch",), {"default": None,
               "help": "Epoch label (default: the year of each mission). Missions without a date"
               " (no metadata.yaml, no dated folder name) make an epoch without a date: a year as"
               " the label stands in for it where a year is needed (FVS Inv_Year); comparing"
               " needs dates."}),
        Option("scan_date", ("--date",), (f"{_TILE}.scan_date",), {"default": None,
               "callback": _date, "metavar": "YYYY-MM-DD",
               "help": "A plain scan's date (default: its GPS time when adjusted standard, else"
               " the header's creation date); the epoch is its year."}),
        Option("trajectory", ("--trajectory",), (f"{_TILE}.trajectory",), {"default": None,
               "type": click.Path(exists=True, dir_okay=False, path_type=Path),
               "help": "A plain scan's trajectory (time, x, y, z CSV/TXT in the scan's CRS and"
               " GPS time base, as SLAM scanners export it): payloads follow it (~20 m of travel"
               " each), for footprints and Voronoi cells."}),
        Option("replace_missions", ("--replace",), (f"{_TILE}.replace_missions",),
               {"is_flag": True, "help": "A mission whose name the catalog holds, tiled from"
                " another folder, replaces it (else refused). Re-tiling a mission from its own"
                " folder needs no --replace."}),
        Option("no_align", ("--no-align",), (f"{_TILE}.align",), {"is_flag": True,
               "help": "Place each mission by its own GNSS fit alone (default: missions given"
               " together that overlap are registered to each other on their stems and ground,"
               " and placed by one graph with their GNSS)."}, lambda v, p: not v),
        Option("accept_poor_georeference", ("--accept-poor-georeference",),
               (f"{_TILE}.accept_poor_georeference",), {"is_flag": True,
               "help": "Tile even when a GNSS fit's RMSE is far beyond the fixes' stated"
               " accuracy."}),
        Option("overwrite", ("--overwrite",), (f"{_TILE}.overwrite",),
               {"is_flag": True, "help": "Replace outputs that already exist."}),
        # enrichment
        Option("epochs", ("--epoch",), (f"{_ENRICH}.epochs",), {"multiple": True,
               "help": "Epoch(s) to enrich (default: all)."}),
        Option("pixel_size", ("--pixel",), (f"{_ENRICH}.pixel_size",), {"type": float,
               "default": 1.0, "show_default": True,
               "help": "DTM/CHM/density pixel size in metres (must divide the cell size)."}),
        Option("halo", ("--halo",), (f"{_ENRICH}.halo",), {"type": float, "default": 10.0,
               "show_default": True, "help": "Metres of neighbouring tiles each stand is"
               " processed with (> a crown radius)."}),
        Option("height_break", ("--height-break",), (f"{_ENRICH}.height_break",),
               {"type": float, "default": 2.0, "show_default": True,
                "help": "Height above ground (m) separating canopy from ground and understory"
                " in metrics."}),
        Option("rigidness", ("--rigidness",), (f"{_ENRICH}.rigidness",), {"type": int,
               "default": 1, "show_default": True,
               "help": "CSF cloth rigidness: 1 steep terrain, 2 relief, 3 flat."}),
        Option("min_observed_fraction", ("--min-observed",),
               (f"{_ENRICH}.min_observed_fraction", f"{_COMPARE}.min_observed_fraction"),
               {"type": float, "default": 0.25, "show_default": True,
                "help": "Least share (0 to 1) of a stand's area observed (by both epochs, for a"
                " change) for its metrics or change to be reported."}),
        Option("min_density_pts_m2", ("--min-density",), (f"{_ENRICH}.min_density_pts_m2",),
               {"type": float, "default": 2.0, "show_default": True,
                "help": "Least points per m2 of observed ground for a stand's metrics to be"
                " reported."}),
        # comparison
        Option("epoch_from", ("--from",), (f"{_COMPARE}.epoch_from",), {"default": None,
               "help": "Earlier epoch (default: the first)."}),
        Option("epoch_to", ("--to",), (f"{_COMPARE}.epoch_to",), {"default": None,
               "help": "Later epoch (default: the last)."}),
        Option("other_catalog", ("--other",), (f"{_COMPARE}.other_catalog",), {"default": None,
               "type": Location(click.Path(exists=True, file_okay=False, path_type=Path)),
               "help": "Take --to from this catalog (a folder or an object-storage URL; it"
               " must be on the same grid); --from and --to then default to the first epoch of"
               " CATALOG and the last of this one."}),
        Option("max_distance", ("--max-distance",), (f"{_COMPARE}.max_distance",),
               {"type": float, "default": 2.0, "show_default": True,
                "help": "Farthest a tree may be from its position in the earlier epoch to match"
                " (m)."}),
        # execution
        Option("workers", ("--workers",), (f"{_RUN}.workers",), {"type": int, "default": None,
               "help": "Run on a local dask cluster of N worker processes (default: this"
               " process)."}),
        Option("scheduler", ("--scheduler",), (f"{_RUN}.scheduler",), {"metavar": "ADDRESS",
               "help": "Run on an existing dask.distributed cluster (tcp://host:port); every"
               " worker must reach the catalog folder at the same path. The catalog is written"
               " only from here."}),
        Option("shared_folder", ("--shared-folder/--no-shared-folder",),
               (f"{_RUN}.shared_folder",), {"default": True, "show_default": True,
               "help": "Whether the cluster's workers reach this machine's folders. With"
               " --no-shared-folder (a catalog in object storage only) workers get each"
               " cell's points from here and put their tiles in the object storage."}),
        Option("memory_mb", ("--memory",), (f"{_RUN}.memory_mb",), {"type": int,
               "default": _default_memory_mb,
               "show_default": "a quarter of the available RAM, 256 to 4096 MB",
               "help": "Memory budget in MB of this process (and of each dask worker): chunks"
               " are sized, reads and writes ahead limited, and the partition engine spills to"
               " disk by it. tile's peak stays within 1.1x the budget plus the interpreter's"
               " own (~200 MB); enrich's comes close (at 512 on 20 M points: 768-811 MB) and"
               " exceeds it where one cell and its buffer do not fit (it says so)."}),
        Option("lock_timeout", ("--lock-timeout",), (f"{_RUN}.lock_timeout",), {"type": float,
               "default": _default_lock_timeout, "show_default": "30",
               "help": "Seconds to wait while another process writes (or reads) the catalog,"
               " then fail cleanly."}),
    )
}
# fmt: on

#: The options of each stage, in the order ``--help`` lists them.
TILE = (
    "cell_size",
    "levels",
    "voronoi",
    "crs",
    "anchor",
    "buffer",
    "las",
    "copc",
    "method",
    "epoch",
    "scan_date",
    "trajectory",
    "replace_missions",
    "no_align",
    "accept_poor_georeference",
)
ENRICH = (
    "epochs",
    "pixel_size",
    "halo",
    "height_break",
    "rigidness",
    "min_observed_fraction",
    "min_density_pts_m2",
)
COMPARE = ("epoch_from", "epoch_to", "other_catalog", "max_distance", "min_observed_fraction")
CLUSTER = ("workers", "scheduler", "shared_folder", "memory_mb", "lock_timeout")

overwrite_option = REGISTRY["overwrite"]


def options(*names: str) -> Callable[[F], F]:
    """The options ``names`` (each once, in this order) on a command."""
    chosen = list(dict.fromkeys(names))
    flags = [d for n in chosen for decl in REGISTRY[n].decls for d in decl.split("/")]
    if len(set(flags)) != len(flags):
        raise ValueError(f"a flag is given twice among {chosen}")

    def decorate(command: F) -> F:
        for name in reversed(chosen):  # click lists them in the order given
            command = REGISTRY[name](command)
        return command

    return decorate


def build(cls: Callable[..., T], params: Mapping[str, Any], **extra: Any) -> T:
    """An options class (or an ``Execution``) from a command's parameters: every registered
    option among ``params`` that sets one of its fields, plus ``extra``."""
    prefix = f"{getattr(cls, '__name__', '')}."
    values: dict[str, Any] = {}
    for name, value in params.items():
        option = REGISTRY.get(name)
        if option is None:
            continue
        for target in option.fields:
            if target.startswith(prefix):
                field_name = target[len(prefix) :]
                convert = option.convert
                values[field_name] = value if convert is None else convert(value, params)
    return cls(**values, **extra)


def execution(params: Mapping[str, Any], quiet: bool) -> Any:
    """The :class:`~standgrid.engine.execution.Execution` of a command's parameters, its
    progress on stderr (none with ``quiet``)."""
    from standgrid.engine.execution import Execution

    return build(Execution, params, progress=TerminalProgress(quiet))


def option_of(name: str) -> Option | None:
    """The option that sets the library option ``name`` (a field's name), or None."""
    for option in REGISTRY.values():
        if name == option.name or any(t.endswith(f".{name}") for t in option.fields):
            return option
    return None


_OPTION_NAME = re.compile(r"\boption ([a-z][a-z0-9_]*)(:?)")


def say_flags(text: str) -> str:
    """A library message for the command line: each ``option <name>`` it names is said as
    the flag that sets it (``option lock_timeout`` -> ``--lock-timeout``; ``option anchor``
    -> ``--anchor LAT LON ALT YAW``, but ``--anchor:`` where it heads a message)."""

    def flag(match: re.Match[str]) -> str:
        option = option_of(match.group(1))
        if option is None:
            return match.group(0)
        return option.flag + ":" if match.group(2) else option.usage

    return _OPTION_NAME.sub(flag, text)


def catalog_argument(exists: bool = True) -> Callable[[F], F]:
    """The CATALOG argument: a catalog folder or an object-storage URL."""
    path = click.Path(exists=exists, file_okay=False, path_type=Path)
    return click.argument("catalog", type=Location(path))


def mission_argument(nargs: int = 1, scans: bool = False, urls: bool = False) -> Callable[[F], F]:
    """A mission folder argument (one, or several with ``nargs=-1``); ``scans``: plain scan
    files (LAS/LAZ/COPC, VPC) are taken too; ``urls``: object-storage URLs too."""
    path = click.Path(exists=True, file_okay=scans, path_type=Path)
    return click.argument(
        "missions" if nargs != 1 else "mission",
        nargs=nargs,
        required=True,
        type=Location(path) if urls else path,
    )


def output_option(required: bool = True, help: str = "Output folder.") -> Callable[[F], F]:
    return click.option(
        "-o",
        "--output",
        required=required,
        type=Location(click.Path(path_type=Path)),
        help=help + " An object-storage URL (s3://bucket/prefix) holds it there.",
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
