"""Frozen, typed views of the missions and epochs recorded in ``catalog.json``.

The JSON format is unchanged: a record is read from it (:meth:`MissionRecord.from_json`,
:meth:`EpochRecord.from_json`) and pipelines read these instead of raw dict keys. Pipelines write
through the transaction's typed methods (:meth:`Transaction.record_mission`,
``settle_epoch``, ``mark_enriched``, ``record_comparison``, ...); only ``standgrid.catalog``
touches the JSON itself.
"""

from __future__ import annotations

import copy
import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

ENRICHED = "enriched"
STALE = "stale"
NOT_ENRICHED = "not enriched"

#: Keys of a mission entry that :class:`MissionRecord` names; any other key is in ``extra``.
_MISSION_KEYS = (
    "number",
    "epoch",
    "date",
    "path",
    "georeference",
    "payload_count",
    "point_count",
    "tiles",
    "ingested",
    "robot",
    "place",
    "unit",
    "sensors",
)


@dataclass(frozen=True)
class MissionRecord:
    """One ingested mission: its number (LAS ``point_source_id``), epoch, source and tiles."""

    name: str
    number: int
    epoch: str
    date: str
    path: str | None = None
    georeference: Mapping[str, Any] | None = None
    payload_count: int = 0
    point_count: int = 0
    tiles: tuple[str, ...] = ()
    ingested: str | None = None
    robot: str = ""
    place: str = ""
    unit: str = ""
    sensors: tuple[str, ...] = ()
    extra: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def from_json(cls, name: str, entry: Mapping[str, Any]) -> MissionRecord:
        georeference = entry.get("georeference")
        return cls(
            name=name,
            number=int(entry["number"]),
            epoch=str(entry.get("epoch", "")),
            date=str(entry.get("date") or ""),
            path=None if entry.get("path") is None else str(entry["path"]),
            georeference=copy.deepcopy(dict(georeference)) if georeference else None,
            payload_count=int(entry.get("payload_count", 0)),
            point_count=int(entry.get("point_count", 0)),
            tiles=tuple(str(t) for t in entry.get("tiles", ())),
            ingested=None if entry.get("ingested") is None else str(entry["ingested"]),
            robot=str(entry.get("robot") or ""),
            place=str(entry.get("place") or ""),
            unit=str(entry.get("unit") or ""),
            sensors=tuple(str(s) for s in entry.get("sensors", ()) or ()),
            extra=copy.deepcopy({k: v for k, v in entry.items() if k not in _MISSION_KEYS}),
        )


@dataclass(frozen=True)
class TilingSettings:
    """How tiles are written: the buffer copied around each cell (m) and the file format."""

    buffer: float = 0.0
    laz: bool = True
    #: COPC (Cloud Optimized Point Cloud: LAZ 1.4 in octree order, streamable by range
    #: requests); implies ``laz``
    copc: bool = False

    @classmethod
    def from_json(cls, entry: Mapping[str, Any] | None) -> TilingSettings:
        entry = entry or {}
        return cls(
            buffer=float(entry.get("buffer", 0.0)),
            laz=bool(entry.get("laz", True)),
            copc=bool(entry.get("copc", False)),
        )

    def to_json(self) -> dict[str, Any]:
        return {"buffer": self.buffer, "laz": self.laz, "copc": self.copc}


@dataclass(frozen=True)
class EpochRecord:
    """One epoch (campaign): its date, missions and enrichment state."""

    label: str
    date: str | None
    missions: tuple[str, ...]
    enriched: bool = False
    enrichment: Mapping[str, Any] | None = None
    invalidated: Mapping[str, Any] | None = None
    comparisons_invalidated: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    #: how its tiles were written (None: not recorded, an older catalog)
    tiling: TilingSettings | None = None

    @classmethod
    def from_json(cls, label: str, entry: Mapping[str, Any]) -> EpochRecord:
        def optional(key: str) -> Any:
            value = entry.get(key)
            return copy.deepcopy(dict(value)) if value else None

        return cls(
            label=label,
            date=str(entry["date"]) if entry.get("date") else None,
            missions=tuple(str(m) for m in entry.get("missions", ())),
            enriched=bool(entry.get("enriched")),
            enrichment=optional("enrichment"),
            invalidated=optional("invalidated"),
            comparisons_invalidated=copy.deepcopy(dict(entry.get("comparisons_invalidated") or {})),
            tiling=TilingSettings.from_json(entry["tiling"]) if entry.get("tiling") else None,
        )

    @property
    def state(self) -> str:
        """``enriched``, ``stale`` (enriched, then re-tiled) or ``not enriched``."""
        return ENRICHED if self.enriched else STALE if self.invalidated else NOT_ENRICHED


def enrichment_stamp(entry: Mapping[str, Any]) -> str | None:
    """The identity of an epoch's current enrichment, from its ``catalog.json`` entry (None
    when it is not enriched): the ``enrichment_id`` each enrich records, or for a catalog
    enriched before ids were recorded, a digest of the enrichment summary. A comparison
    against another catalog records it, so it can tell when that epoch changed since."""
    if not entry.get("enriched"):
        return None
    if entry.get("enrichment_id"):
        return str(entry["enrichment_id"])
    summary = json.dumps(entry.get("enrichment") or {}, sort_keys=True, default=str)
    return "sha256:" + hashlib.sha256(summary.encode()).hexdigest()[:32]
