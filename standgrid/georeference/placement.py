"""How a mission's clouds get into a catalog's CRS: a georeference fit, or clouds already projected.

:func:`place_mission` decides (clouds in a projected CRS: no fit; an explicit anchor; else the
mission's own georeference) and checks the fit's quality. :class:`ToCatalog` is the
picklable recipe that brings one payload's points into the catalog CRS; it builds its
pyproj objects where it runs (this process or a dask worker), once per process.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from standgrid.errors import CatalogError, CRSError, GeoreferenceError

if TYPE_CHECKING:
    from standgrid.georeference.fit import GeoreferenceFit
    from standgrid.georeference.project import MapProjector
    from standgrid.mission.model import Mission, Payload

#: Projectors and transformers built in this process, by :attr:`ToCatalog.key` (unique per
#: recipe; a dask worker keeps them across the tasks of a run).
_BUILT: dict[str, Any] = {}
_BUILT_MAX = 64


@dataclass(frozen=True)
class Placement:
    """A mission's placement: a map -> ENU ``fit``, or (``fit`` None) the projected CRS its
    clouds are already in (``source_crs``)."""

    fit: GeoreferenceFit | None
    source_crs: str | None = None

    def to_catalog(self, crs: str, name: str) -> ToCatalog:
        """The recipe into the catalog CRS ``crs`` (``name``: the mission's, for messages)."""
        import uuid

        # a key unique to this recipe: what a process builds for it is never another's
        return ToCatalog(self.fit, self.source_crs, crs, f"{name}:{uuid.uuid4().hex}")

    def record(self) -> dict[str, Any]:
        """What the catalog stores about how the mission was placed."""
        if self.fit is None:
            return {"format": "standgrid.georeference/1", "method": "projected",
                    "source_crs": self.source_crs}  # fmt: skip
        return self.fit.to_dict()

    def summary(self) -> dict[str, Any]:
        """The headline figures of the placement (the tile report's ``georeference``)."""
        if self.fit is None:
            return {"method": "projected", "source_crs": self.source_crs, "fixes_used": 0,
                    "fixes_rejected": 0, "rmse_horizontal_m": None,
                    "uncertainty": None}  # fmt: skip
        return fit_summary(self.fit)


@dataclass(frozen=True)
class ToCatalog:
    """Points of one mission into the catalog CRS (picklable; pyproj objects built lazily)."""

    fit: GeoreferenceFit | None
    source_crs: str | None
    crs: str
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
                import pyproj

                found = pyproj.Transformer.from_crs(self.source_crs, self.crs, always_xy=True)
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
    crs: str = "auto",
    anchor: tuple[float, float, float, float] | None = None,
    method: str = "yaw2d",
    accept_poor: bool = False,
) -> Placement:
    """How the mission gets into a catalog: clouds already projected (no fit), an explicit
    ``anchor`` ``(lat, lon, alt, yaw_deg)``, or its own georeference (pose-graph anchor or
    GNSS fit, refused when far beyond the fixes' accuracy unless ``accept_poor``)."""
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
                "GNSS_LLA_TO_MAP in the pose graph, an explicit --anchor LAT LON ALT YAW, "
                "or clouds already in a projected CRS: payload_clouds_in_utm/ or LAS/LAZ "
                "with a CRS)",
                path=exc.path or mission.path,
                line=exc.line,
            ) from exc
    if not accept_poor:
        check_fit_quality(fit, source=gnss_file(mission))
    return Placement(fit)


def cloud_payloads(mission: Mission) -> list[Payload]:
    """The point-cloud payloads (a strict mission attaches every one to a node)."""
    return [p for p in mission.payloads if p.kind == "point_cloud"]


def projected_crs(mission: Mission, crs: str = "auto") -> str:
    """The one projected CRS of a mission's projected clouds: their files' own (LAS/LAZ),
    else ``crs`` (PCD/PLY in ``payload_clouds_in_utm/`` carry none)."""
    from standgrid.georeference import crs_to_text, resolve_crs

    clouds = cloud_payloads(mission)
    own = {p.crs for p in clouds if p.crs is not None}
    if len(own) > 1:
        raise CRSError(
            f"the mission's clouds are in several CRSs: {sorted(own)}", path=mission.path
        )
    if own and len(own) == 1 and all(p.crs is not None for p in clouds):
        return own.pop()
    if crs in ("auto", "", None):
        folder = clouds[0].path.parent.name
        raise CRSError(
            f"the clouds in {folder}/ are in a projected CRS their files do not name: give it "
            "with --crs EPSG:XXXX (it is also the catalog's CRS)",
            path=mission.path,
        )
    text = crs_to_text(resolve_crs(crs))
    if own and own != {text}:
        raise CRSError(
            f"some clouds carry the CRS {own.pop()}, --crs says {text}", path=mission.path
        )
    return text


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
