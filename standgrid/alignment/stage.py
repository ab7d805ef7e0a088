"""Align missions to each other: landmarks -> pairwise registration -> mission graph ->
corrected placements (the stage between georeferencing and tiling).

:func:`align_missions` takes missions with their GNSS (or projected) placements and returns
new placements: a fitted mission's map -> ENU transform re-fitted to its trajectory moved
by the graph's correction (so tiling, the trajectories and the fixes' residuals all use
it), with what was aligned, against what and how recorded in ``Placement.alignment``.
A mission that registers with none keeps its GNSS placement, with the reason.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from standgrid.alignment.graph import (
    GNSS_BIAS_M,
    Prior,
    gnss_prior,
    held_prior,
    solve,
    unplaced_prior,
)
from standgrid.alignment.landmarks import Landmarks, mission_landmarks
from standgrid.alignment.register import RegisterOptions, Registration, register, register_global
from standgrid.engine import SILENT, Progress
from standgrid.errors import NotGeoreferencedError

if TYPE_CHECKING:
    from standgrid.georeference.placement import Placement
    from standgrid.mission.model import Mission

FloatArray = NDArray[np.float64]

#: Missions whose trajectories come closer than this (m) are tried for registration.
OVERLAP_REACH_M = 30.0
#: A GNSS prior the forest moves by more than this many sigmas is named in a warning.
MISFIT_SIGMAS = 3.0


@dataclass(frozen=True)
class AlignOptions:
    """How to align (see :mod:`standgrid.alignment`)."""

    register: RegisterOptions = field(default_factory=RegisterOptions)
    #: Horizontal RMS (m) of the GNSS bias per recording assumed for non-RTK fixes.
    gnss_bias_m: float = GNSS_BIAS_M
    #: Missions held where they are (the reference), by name.
    hold: tuple[str, ...] = ()
    #: The absolute DRMS 1-sigma (m) of held missions, by name, where known: added to the
    #: 1-sigma of the missions placed against them.
    held_sigma: tuple[tuple[str, float], ...] = ()


@dataclass(frozen=True, eq=False)
class PlacedLandmarks:
    """A mission's landmarks brought into the catalog CRS by its current placement."""

    name: str
    stems: FloatArray
    points: FloatArray
    nodes: FloatArray


@dataclass
class AlignResult:
    """New placements by mission name, the registrations tried and the warnings."""

    placements: dict[str, Placement]
    registrations: list[Registration]
    missions: dict[str, dict[str, Any]]
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "missions": self.missions,
            "registrations": [r.to_dict() for r in self.registrations],
            "warnings": self.warnings,
        }


#: ``Placement.alignment`` of a mission placed only provisionally (no GNSS, no anchor).
PROVISIONAL = {"provisional": True}


def is_provisional(placement: Placement) -> bool:
    return bool((placement.alignment or {}).get("provisional"))


def provisional_placement(mission: Mission) -> Placement:
    """A mission with neither GNSS nor anchor, put where its metadata says it was (its map
    frame turned anyhow) until registration places it; raises NotGeoreferencedError
    without such a location."""
    from standgrid.georeference import fit_from_anchor
    from standgrid.georeference.placement import Placement

    meta = mission.metadata
    if meta is None or meta.gnss is None:
        raise NotGeoreferencedError(
            "no GNSS fixes, no pose-graph anchor and no location in metadata.yaml: "
            "give option anchor",
            path=mission.path,
            option="anchor",
        )
    lat, lon, alt = meta.gnss
    return Placement(fit_from_anchor(lat, lon, alt, 0.0), None, dict(PROVISIONAL))


def _to_crs(placement: Placement, crs: str, name: str) -> Any:
    """map (or source CRS) points -> catalog CRS, exactly."""
    to_catalog = placement.to_catalog(crs, name)
    if placement.fit is None:
        return to_catalog.projected_points
    return to_catalog.projector.exact


def place_landmarks(marks: Landmarks, placement: Placement, crs: str) -> PlacedLandmarks:
    """``marks`` (in the mission's frame) in the catalog CRS under ``placement``."""
    to = _to_crs(placement, crs, marks.name)
    stems = (
        np.column_stack([to(marks.stems[:, :3]), marks.stems[:, 3]])
        if len(marks.stems)
        else np.zeros((0, 4))
    )
    return PlacedLandmarks(marks.name, stems, to(marks.points), to(marks.nodes))


def _overlap(a: PlacedLandmarks, b: PlacedLandmarks) -> bool:
    if not len(a.nodes) or not len(b.nodes):
        return False
    from scipy.spatial import cKDTree

    d, _ = cKDTree(a.nodes[:, :2]).query(b.nodes[:, :2], distance_upper_bound=OVERLAP_REACH_M)
    return bool(np.isfinite(d).any())


def align_missions(
    items: Sequence[tuple[Mission, Placement]],
    crs: str,
    options: AlignOptions = AlignOptions(),
    *,
    progress: Progress = SILENT,
    landmarks: dict[str, Landmarks] | None = None,
) -> AlignResult:
    """Align ``items`` (missions and their current placements) in the catalog CRS ``crs``;
    ``landmarks``: those already found, by mission name (else found here)."""
    # in name order: the same missions give the same placements however they were listed
    items = sorted(items, key=lambda item: item[0].name)
    names = [m.name for m, _ in items]
    placements = {m.name: p for m, p in items}
    found = dict(landmarks or {})
    for mission, _ in items:
        if mission.name not in found:
            progress.status(f"aligning: landmarks of {mission.name}")
            found[mission.name] = mission_landmarks(mission)
    placed = {n: place_landmarks(found[n], placements[n], crs) for n in names}
    registrations: list[Registration] = []
    held = set(options.hold) | {n for n in names if placements[n].fit is None}
    unplaced = {n for n in names if is_provisional(placements[n])}
    for i, fixed in enumerate(names):
        for moving in names[i + 1 :]:
            if {fixed, moving} <= held or {fixed, moving} <= unplaced:
                continue
            if fixed in unplaced:
                fixed, moving = moving, fixed
            if moving in unplaced:
                progress.status(f"aligning: {moving} onto {fixed} (global search)")
                reg = register_global(placed[moving], placed[fixed], options.register)
            elif _overlap(placed[fixed], placed[moving]):
                progress.status(f"aligning: {moving} onto {fixed}")
                reg = register(placed[moving], placed[fixed], options.register)
            else:
                continue
            registrations.append(reg)
    linked_now = {n for r in registrations if r.accepted for n in (r.moving, r.fixed)}
    lost = sorted(unplaced - linked_now)
    if lost:
        reasons = "; ".join(r.reason for r in registrations if not r.accepted and r.moving in lost)
        raise NotGeoreferencedError(
            f"{', '.join(lost)}: no GNSS, and no mission given or in the catalog registers "
            f"with it ({reasons or 'none overlaps'}): give option anchor",
            option="anchor",
        )
    priors: dict[str, Prior] = {}
    for mission, placement in items:
        nodes = placed[mission.name].nodes
        centre = nodes.mean(axis=0) if len(nodes) else np.zeros(3)
        if placement.fit is None:
            priors[mission.name] = held_prior(centre, "plain scans in the CRS: held")
        elif mission.name in unplaced:
            priors[mission.name] = unplaced_prior(centre)
        elif mission.name in options.hold:
            priors[mission.name] = held_prior(centre, "held as the reference")
        else:
            priors[mission.name] = gnss_prior(
                placement.fit, found[mission.name].nodes, centre, options.gnss_bias_m
            )
    solution = solve(names, priors, registrations)
    linked = {n for r in registrations if r.accepted for n in (r.moving, r.fixed)}
    result = AlignResult({}, registrations, {})
    known = dict(options.held_sigma)
    for mission, placement in items:
        n = mission.name
        corr = solution.corrections[n]
        nodes = placed[n].nodes
        partners = {
            r.fixed if r.moving == n else r.moving
            for r in registrations
            if r.accepted and n in (r.moving, r.fixed)
        }
        sigma_h = float(corr.sigma_at(nodes[:, :2]).max()) if len(nodes) else math.nan
        # placed against held missions: their own absolute uncertainty comes along
        refs = [known[r] for r in partners if r in known]
        if refs and n not in held:
            sigma_h = math.hypot(sigma_h, min(refs))
        moved = corr.apply(nodes) - nodes if len(nodes) else np.zeros((0, 3))
        shift = float(np.hypot(moved[:, 0], moved[:, 1]).max()) if len(moved) else 0.0
        info: dict[str, Any] = {
            "aligned": n in linked,
            "registered_with": sorted(partners),
            "prior": priors[n].how,
            "sigma_prior_m": None if n in unplaced else round(priors[n].sigma_at(nodes), 4),
            "held": n in held,
            "sigma_h_m": None if n in held else round(sigma_h, 4),
            "sigma_rel_m": None
            if math.isnan(solution.sigma_rel[n])
            else round(solution.sigma_rel[n], 4),
            "moved_m": round(shift, 4),
            "dz_m": round(corr.dz, 4),
            "stems": found[n].n_stems,
        }
        misfit = solution.prior_misfit[n]
        if n in linked and misfit > MISFIT_SIGMAS and placement.fit is not None:
            result.warnings.append(
                f"{n}: its GNSS disagrees with the forest: the missions it shares stems with "
                f"move it {shift:.2f} m ({misfit:.1f} x its GNSS 1-sigma)"
            )
        for r in registrations:
            if not r.accepted and n == r.moving:
                result.warnings.append(f"{r.moving} onto {r.fixed}: not registered: {r.reason}")
        result.missions[n] = info
        if n not in linked or placement.fit is None:
            result.placements[n] = replace(placement, alignment={**info, "aligned": False})
            continue
        result.placements[n] = _corrected(mission, placement, crs, corr, info)
    return result


def _corrected(
    mission: Mission, placement: Placement, crs: str, corr: Any, info: dict[str, Any]
) -> Placement:
    """The placement whose map -> ENU transform puts the trajectory where ``corr`` moves it."""
    from standgrid.georeference.fit import GeoreferenceFit, solve_yaw2d
    from standgrid.georeference.placement import Placement, held_placement
    from standgrid.georeference.project import MapProjector

    fit = placement.fit
    assert fit is not None
    _, nodes_map = mission.trajectory()
    if len(nodes_map) < 2:
        spread = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0]])
        nodes_map = np.asarray(nodes_map).reshape(-1, 3)[:1] + spread
    projector = MapProjector(fit, crs)
    target_crs = corr.apply(projector.exact(nodes_map))
    enu = MapProjector(GeoreferenceFit.without_fixes(fit.lla_ref, np.eye(4), "enu"), crs)
    target_enu = enu.to_map(target_crs)
    w = np.ones(len(nodes_map))
    T = solve_yaw2d(nodes_map, target_enu, w, w)
    check = np.abs(MapProjector(replace(fit, T_enu_map=T), crs).exact(nodes_map) - target_crs)
    record = {"T_enu_map": T.tolist(), "lla_ref": list(fit.lla_ref), "method": "aligned"}
    held = held_placement(mission, record)
    info = {**info, "refit_max_m": round(float(check.max()), 6)}
    assert held.fit is not None
    return Placement(replace(held.fit, uncertainty=fit.uncertainty), None, info)
