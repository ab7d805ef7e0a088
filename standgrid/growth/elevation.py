"""A stand's elevation above sea level, from how its epoch's missions were placed.

standgrid's heights are WGS 84 ellipsoidal for missions placed by a GNSS fit or an anchor
(a geoid model turns them into heights above sea level), and those of the source's vertical
datum for already-projected clouds (unknown to standgrid: used only when the user says they
are above sea level). Used by the FVS export's ``ElevFt`` (docs/FVS.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from standgrid.catalog import Catalog
from standgrid.catalog.records import MissionRecord
from standgrid.georeference.geoid import GeoidModel, NoGeoidModel

#: A mission's heights: WGS 84 ellipsoidal (placed by a GNSS fit or an anchor), those of its
#: already-projected clouds (the source's vertical datum), or not recorded.
ELLIPSOIDAL, PROJECTED, UNRECORDED = "ellipsoidal", "projected", "unrecorded"
_NULL = "ElevFt is NULL (FVS uses its variant default)"


@dataclass(frozen=True)
class EpochElevation:
    """How an epoch's ``ElevFt`` is made from its DTM heights h: H = h - N through
    ``geoid``, H = h (``geoid`` None, ``reference`` set), or not at all (``null_reason``)."""

    geoid: GeoidModel | None = None
    reference: str | None = None
    null_reason: str | None = None
    #: H = h because the user says the clouds' heights are above sea level
    user_says_above_sea_level: bool = False


def mission_height_kind(record: MissionRecord) -> str:
    """:data:`ELLIPSOIDAL`, :data:`PROJECTED` or :data:`UNRECORDED`, from how the catalog
    placed the mission (its ``georeference`` record)."""
    if not record.georeference or "method" not in record.georeference:
        return UNRECORDED
    return PROJECTED if record.georeference["method"] == PROJECTED else ELLIPSOIDAL


def epoch_elevation(
    catalog: Catalog,
    epoch: str,
    geoid: GeoidModel | NoGeoidModel,
    heights_above_sea_level: bool = False,
) -> EpochElevation:
    """How ``ElevFt`` is made for ``epoch``, from how its missions were placed.

    Every mission placed by a GNSS fit or an anchor: WGS 84 ellipsoidal heights, minus the
    geoid undulation (NULL without a geoid grid). Every mission already projected: the
    clouds' heights as they are with ``heights_above_sea_level``, else NULL (their vertical
    datum is unknown: the tiler refuses compound CRSs, so no cloud names one). Missions of
    both kinds, or placement not recorded: NULL.
    """
    names = catalog.epoch(epoch).missions
    records = catalog.mission_records
    kinds: dict[str, list[str]] = {}
    for name in names:
        kind = mission_height_kind(records[name]) if name in records else UNRECORDED
        kinds.setdefault(kind, []).append(name)
    if not kinds:
        return EpochElevation(null_reason=f"{_NULL}: the epoch has no mission")
    if UNRECORDED in kinds:
        return EpochElevation(
            null_reason=(
                f"{_NULL}: how mission(s) {', '.join(kinds[UNRECORDED])} were placed is not "
                "recorded (re-tile them), so their heights' vertical reference is unknown"
            )
        )
    if len(kinds) > 1:
        return EpochElevation(
            null_reason=(
                f"{_NULL}: the epoch mixes missions with WGS 84 ellipsoidal heights (GNSS fit or "
                f"anchor: {', '.join(kinds[ELLIPSOIDAL])}) and already-projected clouds (heights "
                f"of their source's vertical datum: {', '.join(kinds[PROJECTED])}); its DTM has "
                "no one vertical reference"
            )
        )
    if ELLIPSOIDAL in kinds:
        if isinstance(geoid, NoGeoidModel):
            return EpochElevation(null_reason=f"{_NULL}: {geoid.reason}")
        return EpochElevation(geoid=geoid, reference=geoid.describe())
    if heights_above_sea_level:
        return EpochElevation(
            reference=(
                "heights of the already-projected clouds, as they are: above sea level as the "
                "user says (--heights-above-sea-level); no geoid applied"
            ),
            user_says_above_sea_level=True,
        )
    return EpochElevation(
        null_reason=(
            f"{_NULL}: heights of already-projected clouds: vertical datum unknown; pass "
            "--heights-above-sea-level if they are"
        )
    )


def above_sea_level(
    elevation: EpochElevation, lon: float, lat: float, height: float
) -> tuple[float, str | None]:
    """A stand's mean DTM ``height`` (m) as height above sea level (m), or NaN and why (None
    when the epoch as a whole has no reference: its ``null_reason`` says why)."""
    if elevation.null_reason is not None:
        return math.nan, None
    if not math.isfinite(height):
        return math.nan, "no DTM height in the stand"
    if elevation.geoid is None:
        return height, None
    result = float(elevation.geoid.orthometric_height(lon, lat, height))
    if not math.isfinite(result):
        return math.nan, (
            f"the geoid grid {elevation.geoid.file} has no undulation at lon {lon:.6f}, "
            f"lat {lat:.6f}"
        )
    return result, None
