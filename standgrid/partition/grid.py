"""The stand grid: a fixed, CRS-anchored square grid with nested levels, and its cell ids.

A :class:`StandGrid` is a value (frozen, hashable, equal by parameters). Its cells are
half-open squares ``[x0 + ix*s, x0 + (ix+1)*s) x [y0 + iy*s, y0 + (iy+1)*s)``; the origin is
anchored to the CRS (never to a data extent), so the same ground gets the same cell ids in
every mission and on every machine.

Canonical cell id text (:class:`CellId`): ``<size>m_E<ix>_N<iy>``, e.g. ``20m_E1234_N-567``.

- ``<size>``: the level's cell size in metres; integer sizes without a decimal point
  (``20``), others as Python's shortest float repr with ``.`` replaced by ``p`` (``2p5``).
- ``E<ix>`` / ``N<iy>``: the column (easting) and row (northing) index of the cell, plain
  decimal integers, ``-`` for negatives, no padding, no ``+``, no leading zeros, no ``-0``.

It is readable, filename-safe (``[0-9A-Za-z_-]`` only) and stable; ``CellId.parse`` is its
exact inverse and rejects every other spelling.
"""

from __future__ import annotations

import functools
import hashlib
import itertools
import json
import math
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from standgrid.crs import CRS, CRSLike
from standgrid.errors import CellIdError, CRSError, GridError

#: Cell indices must fit in a signed 32-bit integer so two of them pack into one int64 key.
INDEX_LIMIT = 2**31
_KEY_LOW_MASK = np.int64(0xFFFFFFFF)

_GRID_FORMAT = "standgrid.StandGrid"
_GRID_VERSION = 1

_INT = r"(?:0|-?[1-9][0-9]*)"
_CELL_RE = re.compile(rf"^([0-9]+(?:p[0-9]+)?)m_E({_INT})_N({_INT})$")


# --- CRS ---------------------------------------------------------------------------------


def grid_crs(crs: CRSLike) -> CRS:
    """A grid's CRS: projected and explicit (``CRSError`` for ``'auto'``, PROJ strings and
    non-projected CRSs)."""
    if isinstance(crs, str) and crs.strip().lower() == "auto":
        raise CRSError("a grid needs an explicit CRS, not 'auto'")
    return CRS.of(crs).projected()


def normalise_crs(crs: CRSLike) -> str:
    """The canonical stored form of a grid CRS (:func:`grid_crs`'s text): ``"EPSG:XXXX"``
    when it round-trips, else WKT2."""
    return grid_crs(crs).text


# --- cell ids ----------------------------------------------------------------------------


def format_size(size: float) -> str:
    """The size token of a cell id: ``20`` for 20.0, ``2p5`` for 2.5."""
    if not (math.isfinite(size) and size > 0):
        raise GridError(f"cell size must be a positive finite number, got {size!r}")
    if size.is_integer() and size < 2**53:
        return str(int(size))
    text = repr(float(size))
    if "e" in text or "E" in text:
        raise GridError(f"cell size {size!r} has no fixed-point spelling for a cell id")
    return text.replace(".", "p")


@functools.total_ordering
@dataclass(frozen=True, eq=True)
class CellId:
    """One grid cell: level cell ``size`` (metres), column ``ix``, row ``iy``.

    Ordered by ``(size, ix, iy)`` — within a level the same order as :attr:`key`.
    """

    size: float
    ix: int
    iy: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "size", float(self.size))
        object.__setattr__(self, "ix", int(self.ix))
        object.__setattr__(self, "iy", int(self.iy))
        format_size(self.size)
        _check_index_range(self.ix, self.iy)

    def __lt__(self, other: object) -> bool:
        if not isinstance(other, CellId):
            return NotImplemented
        return (self.size, self.ix, self.iy) < (other.size, other.ix, other.iy)

    def __str__(self) -> str:
        return f"{format_size(self.size)}m_E{self.ix}_N{self.iy}"

    def __repr__(self) -> str:
        return f"CellId({str(self)!r})"

    @classmethod
    def parse(cls, text: str) -> CellId:
        """The exact inverse of ``str(cell)``; any other spelling raises ``CellIdError``."""
        if not isinstance(text, str):
            raise CellIdError(f"cell id must be text, got {type(text).__name__}: {text!r}")
        match = _CELL_RE.match(text)
        if match is None:
            raise CellIdError(f"not a canonical cell id (<size>m_E<ix>_N<iy>): {text!r}")
        size_text, ix_text, iy_text = match.groups()
        try:
            cell = cls(float(size_text.replace("p", ".")), int(ix_text), int(iy_text))
        except GridError as exc:
            raise CellIdError(f"invalid cell id {text!r}: {exc.message}") from exc
        if str(cell) != text:
            raise CellIdError(f"not a canonical cell id (expected {str(cell)!r}): {text!r}")
        return cell

    @property
    def key(self) -> int:
        """The int64 key of ``(ix, iy)``: ``ix * 2**32 + (iy + 2**31)`` (same order as ids)."""
        return self.ix * 2**32 + (self.iy + INDEX_LIMIT)

    @classmethod
    def from_key(cls, key: int, size: float) -> CellId:
        ix, iy = divmod(int(key), 2**32)
        return cls(size, ix, iy - INDEX_LIMIT)

    def parent(self, target: StandGrid | float) -> CellId:
        """The enclosing cell at the next coarser level of a grid, or at a coarser ``size``."""
        size = target.coarser_size(self.size) if isinstance(target, StandGrid) else float(target)
        ratio = _ratio(size, self.size)
        return CellId(size, self.ix // ratio, self.iy // ratio)

    def children(self, target: StandGrid | float) -> list[CellId]:
        """The cells of the next finer level of a grid (or of a finer ``size``), row-major."""
        size = target.finer_size(self.size) if isinstance(target, StandGrid) else float(target)
        ratio = _ratio(self.size, size)
        return [
            CellId(size, self.ix * ratio + i, self.iy * ratio + j)
            for i in range(ratio)
            for j in range(ratio)
        ]

    def neighbours(self, ring: int = 1) -> list[CellId]:
        """The cells at Chebyshev distance ``1..ring`` (8 for ring 1), sorted."""
        if ring < 1:
            raise GridError(f"ring must be >= 1, got {ring}")
        return [
            CellId(self.size, self.ix + i, self.iy + j)
            for i in range(-ring, ring + 1)
            for j in range(-ring, ring + 1)
            if (i, j) != (0, 0)
        ]


def _ratio(coarse: float, fine: float) -> int:
    ratio = round(coarse / fine)
    if ratio < 1 or float(ratio) * fine != coarse:
        raise GridError(f"cell size {coarse!r} is not an integer multiple of {fine!r}")
    return int(ratio)


def _check_index_range(*indices: int) -> None:
    for value in indices:
        if not -INDEX_LIMIT <= value < INDEX_LIMIT:
            raise GridError(f"cell index {value} is outside the 32-bit range of the grid")


def key_to_index(keys: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Unpack int64 keys (from :meth:`StandGrid.cell_keys`) into ``(ix, iy)``."""
    k = np.asarray(keys, dtype=np.int64)
    return k >> 32, (k & _KEY_LOW_MASK) - INDEX_LIMIT


def index_to_key(ix: ArrayLike, iy: ArrayLike) -> NDArray[np.int64]:
    """Pack ``(ix, iy)`` into int64 keys; key order is ``(ix, iy)`` lexicographic order."""
    ix64 = np.asarray(ix, dtype=np.int64)
    iy64 = np.asarray(iy, dtype=np.int64)
    if ix64.size and (
        ix64.min() < -INDEX_LIMIT
        or ix64.max() >= INDEX_LIMIT
        or iy64.min() < -INDEX_LIMIT
        or iy64.max() >= INDEX_LIMIT
    ):
        raise GridError("cell index outside the 32-bit range of the grid")
    return (ix64 << 32) + (iy64 + INDEX_LIMIT)


# --- the grid ----------------------------------------------------------------------------


def _as_float(value: Any, what: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise GridError(f"{what} must be a number, got {value!r}") from exc
    if not math.isfinite(number):
        raise GridError(f"{what} must be finite, got {value!r}")
    return number


@dataclass(frozen=True)
class StandGrid:
    """A square grid anchored to a projected CRS, with nested levels (finest first).

    ``levels`` defaults to ``(cell_size, 5 * cell_size)`` — 20 m cells inside 1 ha stands.
    Every coarser level is an exact integer multiple of the finer one.
    """

    crs: CRS
    cell_size: float = 20.0
    origin: tuple[float, float] = (0.0, 0.0)
    levels: tuple[float, ...] = field(default=())

    def __post_init__(self) -> None:
        set_ = functools.partial(object.__setattr__, self)
        set_("crs", grid_crs(self.crs))
        size = _as_float(self.cell_size, "cell_size")
        if size <= 0:
            raise GridError(f"cell_size must be positive, got {self.cell_size!r}")
        set_("cell_size", size)
        try:
            x0, y0 = self.origin
        except (TypeError, ValueError) as exc:
            raise GridError(f"origin must be (x0, y0), got {self.origin!r}") from exc
        set_("origin", (_as_float(x0, "origin x0"), _as_float(y0, "origin y0")))
        levels = tuple(_as_float(s, "level size") for s in (self.levels or (size, 5 * size)))
        if levels[0] != size:
            raise GridError(f"the finest level {levels[0]!r} must equal cell_size {size!r}")
        for fine, coarse in itertools.pairwise(levels):
            if not coarse > fine:
                raise GridError(f"levels must grow strictly, finest first: {levels!r}")
            _ratio(coarse, fine)
        for s in levels:
            format_size(s)
        set_("levels", levels)

    # -- levels -------------------------------------------------------------------------

    def level_size(self, level: int = 0) -> float:
        if not 0 <= level < len(self.levels):
            raise GridError(f"level {level} out of range: the grid has levels {self.levels!r}")
        return self.levels[level]

    def level_of(self, size: float) -> int:
        try:
            return self.levels.index(float(size))
        except ValueError:
            raise GridError(
                f"cell size {size!r} is not a level of this grid {self.levels!r}"
            ) from None

    def coarser_size(self, size: float) -> float:
        level = self.level_of(size)
        if level + 1 >= len(self.levels):
            raise GridError(f"{size!r} m is the coarsest level of this grid")
        return self.levels[level + 1]

    def finer_size(self, size: float) -> float:
        level = self.level_of(size)
        if level == 0:
            raise GridError(f"{size!r} m is the finest level of this grid")
        return self.levels[level - 1]

    # -- points -> cells ----------------------------------------------------------------

    def _axis_index(self, v: NDArray[np.float64], v0: float, s: float) -> NDArray[np.int64]:
        idx = np.floor((v - v0) / s)
        # the recomputed bounds decide: v0 + i*s <= v < v0 + (i+1)*s, exactly as bounds() does
        idx -= v < v0 + idx * s
        idx += v >= v0 + (idx + 1) * s
        if idx.size and (idx.min() < -INDEX_LIMIT or idx.max() >= INDEX_LIMIT):
            raise GridError("coordinates fall outside the 32-bit index range of the grid")
        return idx.astype(np.int64)

    def cell_index(
        self, x: ArrayLike, y: ArrayLike, level: int = 0
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Column and row of the half-open cell containing each point (never clamped)."""
        s = self.level_size(level)
        xa = np.asarray(x, dtype=np.float64)
        ya = np.asarray(y, dtype=np.float64)
        if not (np.isfinite(xa).all() and np.isfinite(ya).all()):
            raise GridError("cannot place non-finite coordinates on the grid")
        return self._axis_index(xa, self.origin[0], s), self._axis_index(ya, self.origin[1], s)

    def cell_keys(self, x: ArrayLike, y: ArrayLike, level: int = 0) -> NDArray[np.int64]:
        """One int64 key per point (see :func:`key_to_index`), for vectorised grouping."""
        ix, iy = self.cell_index(x, y, level)
        return index_to_key(ix, iy)

    def key_to_cell(self, key: int, level: int = 0) -> CellId:
        return CellId.from_key(key, self.level_size(level))

    def cell(self, x: float, y: float, level: int = 0) -> CellId:
        ix, iy = self.cell_index(x, y, level)
        return CellId(self.level_size(level), int(ix), int(iy))

    def bounds(self, cell: CellId) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)``: the cell holds xmin <= x < xmax and ymin <= y < ymax."""
        self.level_of(cell.size)
        s = cell.size
        x0, y0 = self.origin
        return (
            float(x0 + np.float64(cell.ix) * s),
            float(y0 + np.float64(cell.iy) * s),
            float(x0 + np.float64(cell.ix + 1) * s),
            float(y0 + np.float64(cell.iy + 1) * s),
        )

    def polygon(self, cell: CellId) -> Any:
        """The cell as a shapely polygon (closed box; the grid itself is half-open)."""
        import shapely

        return shapely.box(*self.bounds(cell))

    def cells_in_bounds(
        self, xmin: float, ymin: float, xmax: float, ymax: float, level: int = 0
    ) -> list[CellId]:
        """Every cell holding some point of the closed box, sorted."""
        if not (xmin <= xmax and ymin <= ymax):
            raise GridError(f"empty bounds ({xmin}, {ymin}, {xmax}, {ymax})")
        ix, iy = self.cell_index([xmin, xmax], [ymin, ymax], level)
        s = self.level_size(level)
        return [
            CellId(s, i, j)
            for i in range(int(ix[0]), int(ix[1]) + 1)
            for j in range(int(iy[0]), int(iy[1]) + 1)
        ]

    def iter_cells(self, keys: ArrayLike, level: int = 0) -> Iterator[CellId]:
        s = self.level_size(level)
        for key in np.asarray(keys, dtype=np.int64).tolist():
            yield CellId.from_key(key, s)

    # -- serialisation ------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": _GRID_FORMAT,
            "version": _GRID_VERSION,
            "crs": self.crs.text,
            "cell_size": self.cell_size,
            "origin": list(self.origin),
            "levels": list(self.levels),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> StandGrid:
        expected = {"format", "version", "crs", "cell_size", "origin", "levels"}
        if not isinstance(data, Mapping) or set(data) != expected:
            keys = sorted(data) if isinstance(data, Mapping) else type(data).__name__
            raise GridError(
                f"a grid definition needs exactly the keys {sorted(expected)}, got {keys}"
            )
        if data["format"] != _GRID_FORMAT or data["version"] != _GRID_VERSION:
            raise GridError(f"unsupported grid format {data['format']!r} v{data['version']!r}")
        return cls(
            crs=data["crs"],
            cell_size=data["cell_size"],
            origin=tuple(data["origin"]),
            levels=tuple(data["levels"]),
        )

    def to_json(self) -> str:
        """Canonical JSON: sorted keys, no spaces, floats as their shortest exact repr."""
        return json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"), allow_nan=False)

    @classmethod
    def from_json(cls, text: str) -> StandGrid:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise GridError(f"grid definition is not JSON: {exc}") from exc
        return cls.from_dict(data)

    @functools.cached_property
    def fingerprint(self) -> str:
        """sha256 hex of the canonical JSON: equal for equal grids, on any machine."""
        return hashlib.sha256(self.to_json().encode("utf-8")).hexdigest()
