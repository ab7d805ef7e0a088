"""A coordinate reference system as a value: parsed once, compared and hashed by its text.

A :class:`CRS` is built from an EPSG code (``32630``), ``"EPSG:32630"`` (or another
authority code such as ``"OGC:CRS84"``), WKT/WKT2 text, a ``pyproj.CRS`` or another
:class:`CRS`; PROJ strings are refused (they leave the datum ambiguous). Its canonical
:attr:`~CRS.text` is ``EPSG:XXXX`` when that code round-trips to an equal CRS, else WKT2_2019:
the form catalog.json, LAS headers and GeoPackages carry. Inside the library a CRS travels as
this value; it becomes text only at a file or JSON boundary. Coordinates are x/y (easting or
longitude first): every transformer is ``always_xy``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Union

from standgrid.errors import CRSError

if TYPE_CHECKING:  # pyproj is imported when a CRS is first parsed (a light ``import``)
    import pyproj

#: What :meth:`CRS.of` accepts.
CRSLike = Union[int, str, "pyproj.CRS", "CRS"]


@dataclass(frozen=True, repr=False)
class CRS:
    """An immutable, hashable CRS; equal when the canonical texts are equal."""

    text: str
    pyproj_crs: pyproj.CRS = field(compare=False, hash=False)

    @classmethod
    def of(cls, spec: CRSLike) -> CRS:
        """The CRS ``spec`` names; :class:`~standgrid.errors.CRSError` naming a bad ``spec``."""
        if isinstance(spec, CRS):
            return spec
        import pyproj

        if isinstance(spec, pyproj.CRS):
            return cls(_canonical_text(spec), spec)
        if isinstance(spec, bool):  # bool is an int subclass: True is not EPSG:1
            raise CRSError(f"not a CRS: {spec!r}")
        if isinstance(spec, int):
            return _from_epsg(spec)
        if isinstance(spec, str):
            return _from_text(spec.strip())
        raise CRSError(f"not a CRS spec: {type(spec).__name__} {spec!r}")

    # --- what it is ----------------------------------------------------------------------

    @functools.cached_property
    def epsg(self) -> int | None:
        """The EPSG code pyproj identifies (``to_epsg()``), or None."""
        return self.pyproj_crs.to_epsg()

    @functools.cached_property
    def authority(self) -> tuple[str, str] | None:
        """``(authority, code)``, e.g. ``("EPSG", "32630")``, or None."""
        return self.pyproj_crs.to_authority()

    @property
    def wkt2(self) -> str:
        """WKT2_2019 text."""
        return str(self.pyproj_crs.to_wkt("WKT2_2019"))

    @property
    def name(self) -> str:
        return str(self.pyproj_crs.name)

    @property
    def is_projected(self) -> bool:
        return bool(self.pyproj_crs.is_projected)

    @property
    def is_geographic(self) -> bool:
        return bool(self.pyproj_crs.is_geographic)

    @property
    def northing_first(self) -> bool:
        """True when the first axis points north or south (``EPSG:4326``: latitude first)."""
        axes = self.pyproj_crs.axis_info
        return bool(axes) and axes[0].direction.lower() in ("north", "south")

    def equivalent(self, other: CRSLike) -> bool:
        """pyproj's equality (the same CRS written two ways), not only the same text."""
        other = CRS.of(other)
        return self == other or bool(self.pyproj_crs == other.pyproj_crs)

    def projected(self) -> CRS:
        """``self`` when it is a projected (metric x/y), non-compound CRS, else
        :class:`~standgrid.errors.CRSError` (standgrid writes WGS 84 ellipsoidal heights)."""
        crs = self.pyproj_crs
        if crs.is_compound:
            raise CRSError(
                f"compound CRS {crs.name!r} refused: standgrid writes WGS 84 ellipsoidal "
                "heights, so give the horizontal projected CRS alone (e.g. its EPSG code)"
            )
        if not crs.is_projected:
            kind = (
                "geographic"
                if crs.is_geographic
                else "geocentric"
                if crs.is_geocentric
                else "non-projected"
            )
            raise CRSError(
                f"{kind} CRS {crs.name!r} refused: give a projected (metric x/y) CRS, "
                "e.g. 'auto' for UTM"
            )
        return self

    # --- transformations -----------------------------------------------------------------

    def transformer_to(self, target: CRSLike) -> pyproj.Transformer:
        """The ``always_xy`` transformer from this CRS to ``target`` (cached; pyproj
        transformers are thread-local inside, so one may serve several threads)."""
        return _transformer(self, CRS.of(target))

    def __repr__(self) -> str:
        return f"CRS({self.text[:60]!r})"

    def __reduce__(self) -> tuple[Any, tuple[str]]:
        return (_from_text, (self.text,))  # the canonical text parses back to an equal CRS

    def __str__(self) -> str:
        return self.text


@functools.lru_cache(maxsize=64)
def _from_epsg(code: int) -> CRS:
    import pyproj
    from pyproj.exceptions import CRSError as PyprojCRSError

    try:
        return CRS.of(pyproj.CRS.from_epsg(code))
    except PyprojCRSError as exc:
        raise CRSError(f"unknown EPSG code {code}") from exc


@functools.lru_cache(maxsize=64)
def _from_text(text: str) -> CRS:
    if text.startswith("+") or "+proj=" in text or text.lower().startswith("proj="):
        raise CRSError(
            f"PROJ strings are not accepted ({text[:40]!r}): give an EPSG code "
            "('EPSG:32630') or WKT2 text, which keep the datum unambiguous"
        )
    if not text:
        raise CRSError("empty CRS spec")
    import pyproj
    from pyproj.exceptions import CRSError as PyprojCRSError

    try:
        return CRS.of(pyproj.CRS.from_user_input(text))
    except PyprojCRSError as exc:
        raise CRSError(f"unknown CRS {text[:80]!r}") from exc


def _canonical_text(crs: pyproj.CRS) -> str:
    """``EPSG:XXXX`` when that code round-trips to an equal CRS, else WKT2_2019."""
    import pyproj
    from pyproj.exceptions import CRSError as PyprojCRSError

    epsg = crs.to_epsg()
    if epsg is not None:
        try:
            if pyproj.CRS.from_epsg(epsg) == crs:
                return f"EPSG:{epsg}"
        except PyprojCRSError:  # pragma: no cover - to_epsg only returns known codes
            pass
    wkt = crs.to_wkt("WKT2_2019")
    if not wkt:
        raise CRSError(f"CRS {crs.name!r} cannot be written as WKT2")
    return str(wkt)


@functools.lru_cache(maxsize=64)
def _transformer(source: CRS, target: CRS) -> pyproj.Transformer:
    import pyproj

    return pyproj.Transformer.from_crs(source.pyproj_crs, target.pyproj_crs, always_xy=True)
