"""How a mission's clouds get into a catalog's CRS: a georeference fit, or clouds already projected.

:func:`place_mission` decides (clouds in a projected CRS: no fit; an explicit anchor; else the
mission's own georeference) and checks the fit's quality. :class:`ToCatalog` is the
picklable recipe that brings one payload's points into the catalog CRS; it builds its
pyproj objects where it runs (this process or a dask worker), once per process.
:func:`held_placement` and :func:`placement_offset` let a catalog keep the placement it used
when a refit moves the mission by less than a tolerance (``TileOptions.placement_tolerance``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from standgrid.crs import CRS, CRSLike
from standgrid.errors import CatalogError, CRSError, GeoreferenceError

if TYPE_CHECKING:
    from standgrid.georeference.fit import GeoreferenceFit
    from standgrid.georeference.project import MapProjector
    from standgrid.mission.model import Mission
    from standgrid.mission.payload import Payload

#: Projectors and transformers built in this process, by :attr:`ToCatalog.key` (unique per
#: recipe; a dask worker keeps them across the tasks of a run).
_BUILT: dict[str, Any] = {}
_BUILT_MAX = 64


@dataclass(frozen=True)
class Placement:
    """A mission's placement: a map -> ENU ``fit``, or (``fit`` None) the projected CRS its
    clouds are already in (``source_crs``)."""

    fit: GeoreferenceFit | None
    source_crs: CRS | None = None
    #: How alignment with other missions moved it (:mod:`standgrid.alignment`), None: GNSS only.
    alignment: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        if self.source_crs is not None:  # text from a catalog record: the value
            object.__setattr__(self, "source_crs", CRS.of(self.source_crs))

    def to_catalog(self, crs: CRSLike, name: str) -> ToCatalog:
        """The recipe into the catalog CRS ``crs`` (``name``: the mission's, for messages)."""
        import uuid

        # a key unique to this recipe: what a process builds for it is never another's
        return ToCatalog(self.fit, self.source_crs, CRS.of(crs), f"{name}:{uuid.uuid4().hex}")

    def record(self) -> dict[str, Any]:
        """What the catalog stores about how the mission was placed."""
        out: dict[str, Any]
        if self.fit is None:
            out = {
                "format": "standgrid.georeference/1",
                "method": "projected",
                "source_crs": _text(self.source_crs),
            }
        else:
            out = self.fit.to_dict()
        if self.alignment is not None:
            out["alignment"] = self.alignment
        return out

    def summary(self) -> dict[str, Any]:
        """The headline figures of the placement (the tile report's ``georeference``)."""
        out: dict[str, Any]
        if self.fit is None:
            out = {
                "method": "projected",
                "source_crs": _text(self.source_crs),
                "fixes_used": 0,
                "fixes_rejected": 0,
                "rmse_horizontal_m": None,
                "uncertainty": None,
            }
        else:
            out = fit_summary(self.fit)
        if self.alignment is not None:
            out["alignment"] = self.alignment
        return out


@dataclass(frozen=True)
class ToCatalog:
    """Points of one mission into the catalog CRS (picklable; pyproj objects built lazily)."""

    fit: GeoreferenceFit | None
    source_crs: CRS | None
    crs: CRS
    key: str

    @property
    def projector(self) -> MapProjector:
        """The map -> catalog CRS projector of a fitted mission."""
        if self.fit is None:
            raise GeoreferenceError(f"{self.key}: projected clouds have no map frame")
        return self._built("projector")

    def transformer(self) -> Any:
        """source CRS -> catalog CRS (x/y only) for projected clouds; None: the same CRS."""
        if self.fit is not None or self.source_crs == self.crs:
            return None
        return self._built("transformer")

    def _built(self, kind: str) -> Any:
        name = f"{kind}:{self.key}"
        found = _BUILT.get(name)
        if found is None:
            if len(_BUILT) >= _BUILT_MAX:
                _BUILT.clear()
            if kind == "projector":
                from standgrid.georeference.project import MapProjector

                assert self.fit is not None
                found = MapProjector(self.fit, self.crs)
            else:
                assert self.source_crs is not None
                found = self.source_crs.transformer_to(self.crs)
            _BUILT[name] = found
        return found

    def base_points(
        self,
        xyz: NDArray[np.float64],
        pose: NDArray[np.float64],
        *,
        out: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64]:
        """Base-frame points of a node at ``pose`` (T_map_base) into the catalog CRS (<= 1 mm);
        ``out`` (may be ``xyz``) may receive them (see :meth:`MapProjector.fast`)."""
        return self.projector.fast(xyz, pose=pose, out=out)

    def projected_points(self, xyz: NDArray[np.float64]) -> NDArray[np.float64]:
        """Points in the source CRS into the catalog CRS (heights as the clouds have them)."""
        transformer = self.transformer()
        if transformer is None:
            return xyz
        x, y = transformer.transform(xyz[:, 0], xyz[:, 1], errcheck=True)
        return np.column_stack([np.asarray(x), np.asarray(y), xyz[:, 2]])


def place_mission(
    mission: Mission,
    *,
    crs: CRSLike = "auto",
    anchor: tuple[float, float, float, float] | None = None,
    method: str = "yaw2d",
    accept_poor: bool = False,
) -> Placement:
    """How the mission gets into a catalog: clouds already projected (no fit), an explicit
    ``anchor`` ``(lat, lon, alt, yaw_deg)``, or its own georeference (pose-graph anchor or
    GNSS fit, refused when far beyond the fixes' accuracy, or far from the location the
    mission's metadata gives, unless ``accept_poor``)."""
    from standgrid.georeference import fit_from_anchor, georeference_mission
    from standgrid.georeference.fit import check_fit_quality

    if mission.is_projected:
        if anchor is not None:
            raise CatalogError(
                "the clouds are already in a projected CRS: an anchor would not be used",
                path=mission.path,
            )
        return Placement(None, projected_crs(mission, crs))
    if anchor is not None:
        fit = fit_from_anchor(*anchor)
    else:
        try:
            fit = georeference_mission(mission, method=method)
        except GeoreferenceError as exc:
            raise type(exc)(
                f"{exc.message} (tiling needs a georeference: GNSS fixes, GNSS_LLA_REF/"
                "GNSS_LLA_TO_MAP in the pose graph, an explicit option anchor, "
                "or clouds already in a projected CRS: payload_clouds_in_utm/ or LAS/LAZ "
                "with a CRS)",
                path=exc.path or mission.path,
                line=exc.line,
                option="anchor",
            ) from exc
    if not accept_poor:
        check_metadata_location(mission, fit)
        check_fit_quality(fit, source=gnss_file(mission))
    return Placement(fit)


def check_metadata_location(mission: Mission, fit: GeoreferenceFit) -> None:
    """Refuse (:class:`~standgrid.errors.MisplacedMissionError`) a fit that puts the mission
    more than :data:`~standgrid.georeference.location.MAX_METADATA_DISTANCE_M` from the
    location its metadata gives (none given: nothing to check)."""
    from standgrid.georeference.location import check_location

    meta = mission.metadata
    if meta is None or meta.gnss is None:
        return
    _, positions = mission.trajectory()
    check_location(
        fit, positions, meta.gnss, source=gnss_file(mission), metadata=mission.layout.metadata
    )


#: The smallest radius of curvature of the WGS 84 ellipsoid (the meridian's at the equator,
#: m); with 1 / cos(latitude) for the grid convergence, what bounds how fast a projection's
#: Jacobian turns or scales per metre of ground.
MIN_EARTH_RADIUS_M = 6_335_439.0


def held_placement(mission: Mission, record: dict[str, Any]) -> Placement:
    """The placement a catalog recorded for ``mission`` (its ``georeference`` record: the
    transform ``T_enu_map`` about ``lla_ref``), with the residuals of the mission's current
    GNSS fixes under that transform (nothing is refitted)."""
    from standgrid.georeference.fit import GeoreferenceFit, evaluate_georeference

    try:
        transform = np.array(record["T_enu_map"], dtype=np.float64).reshape(4, 4)
        lat, lon, alt = (float(v) for v in record["lla_ref"])
        method = str(record["method"])
    except (KeyError, TypeError, ValueError) as exc:
        raise CatalogError(
            f"malformed georeference record of mission {mission.name!r}: {exc!r}", path=mission.path
        ) from exc
    graph, gnss = mission.graph, mission.gnss
    if graph is None or len(graph) == 0 or gnss is None or len(gnss) == 0:
        return Placement(GeoreferenceFit.without_fixes((lat, lon, alt), transform, method))
    fit = evaluate_georeference(
        transform,
        (lat, lon, alt),
        method,
        gnss,
        graph.stamps_ns,
        graph.positions,
        source=gnss_file(mission),
    )
    return Placement(fit)


def placement_offset(
    used: Placement, fresh: Placement, xyz_map: NDArray[np.float64], crs: CRSLike
) -> float:
    """How far (m, 3-D: catalog CRS x, y and ellipsoidal height) ``fresh`` would put any point
    of the convex hull of ``xyz_map`` (map frame, e.g. the corners of every payload's box)
    from where ``used`` puts it: a bound, through the real transforms.

    Both placements are rigid map -> ECEF motions ``A`` followed by the same smooth
    projection ``f`` (ECEF -> CRS). The displacement is ``D(p) = f(A1 p) - f(A0 p) =
    J0 (A1 - A0) p + r(p)``: ``(A1 - A0) p`` is affine in ``p``, so ``|J0 (A1 - A0) p|`` is
    convex and its maximum over the hull is at a vertex, which is among the given points.
    ``f``'s Jacobian turns and scales by at most ``E / (R cos phi)`` across a hull of extent
    ``E`` at latitude ``phi`` (``R`` >= :data:`MIN_EARTH_RADIUS_M`; a transverse Mercator's
    grid convergence turns with ``tan phi / R``), so ``|r| <= 2 (E / (R cos phi)) max |D|``
    (terms in ``|D|^2 / R``, micrometres, aside); the bound returned is the largest ``|D|``
    over the points times ``1 + 4 E / (R cos phi)`` (1.0003 for a 500 m mission at 0 deg,
    1.0006 at 60 deg; ``cos phi`` taken at least 0.05), plus 1 micrometre. It bounds the
    exact transforms: any tiling also rounds coordinates to the 1 mm storage lattice. Raises
    :class:`GeoreferenceError` for projected clouds (no map frame).
    """
    if used.fit is None or fresh.fit is None:
        raise GeoreferenceError("projected clouds have no map frame: no placement offset")
    points = np.asarray(xyz_map, dtype=np.float64).reshape(-1, 3)
    if not len(points):
        return 0.0
    from standgrid.georeference.project import MapProjector

    moved = MapProjector(fresh.fit, crs).exact(points) - MapProjector(used.fit, crs).exact(points)
    largest = float(np.sqrt(np.max(np.einsum("ij,ij->i", moved, moved))))
    extent = float(np.max(np.linalg.norm(points - points.mean(axis=0), axis=1)))
    latitude = np.radians(max(abs(used.fit.lla_ref[0]), abs(fresh.fit.lla_ref[0])))
    radius = MIN_EARTH_RADIUS_M * max(float(np.cos(latitude)), 0.05)
    return largest * (1.0 + 4.0 * extent / radius) + 1e-6


def cloud_payloads(mission: Mission) -> list[Payload]:
    """The point-cloud payloads (a strict mission attaches every one to a node)."""
    return [p for p in mission.payloads if p.kind == "point_cloud"]


def projected_crs(mission: Mission, crs: CRSLike = "auto") -> CRS:
    """The one projected CRS of a mission's projected clouds: their files' own (LAS/LAZ),
    else ``crs`` (PCD/PLY in ``payload_clouds_in_utm/`` carry none)."""
    from standgrid.georeference import resolve_crs

    clouds = cloud_payloads(mission)
    own = {p.crs for p in clouds if p.crs is not None}
    if len(own) > 1:
        texts = sorted(c.text for c in own)
        raise CRSError(f"the mission's clouds are in several CRSs: {texts}", path=mission.path)
    if own and len(own) == 1 and all(p.crs is not None for p in clouds):
        return own.pop()
    if crs in ("auto", "", None):
        folder = clouds[0].path.parent.name
        raise CRSError(
            f"the clouds in {folder}/ are in a projected CRS their files do not name: give it "
            "with option crs (EPSG:XXXX; it is also the catalog's CRS)",
            path=mission.path,
            option="crs",
        )
    wanted = resolve_crs(crs)
    if own and own != {wanted}:
        raise CRSError(
            f"some clouds carry the CRS {own.pop()}, option crs says {wanted}",
            path=mission.path,
            option="crs",
        )
    return wanted


def _text(crs: CRS | None) -> str | None:
    return None if crs is None else crs.text


def gnss_file(mission: Mission) -> Path:
    """The file the mission's GNSS fixes came from (for messages)."""
    gnss = mission.path / "gnss" / "fixes.txt"
    return gnss if gnss.is_file() else mission.path


def fit_summary(fit: GeoreferenceFit) -> dict[str, Any]:
    """The headline figures of a georeference fit."""
    return {
        "method": fit.method,
        "fixes_used": int(fit.n_used),
        "fixes_rejected": int(fit.n_rejected),
        "rejected_by_reason": fit.rejected_by_reason,
        "rmse_horizontal_m": finite_or_none(fit.rmse_m),
        "rmse_vertical_m": finite_or_none(fit.rmse_vertical_m),
        "yaw_deg": fit.yaw_deg,
        "lla_ref": list(fit.lla_ref),
        "uncertainty": None if fit.uncertainty is None else fit.uncertainty.to_dict(),
    }


def finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None
