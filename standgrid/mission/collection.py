"""A folder of missions: find them, read their metadata, search by site, date, robot, sensors."""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from standgrid.errors import MissionNotFoundError, StandgridError
from standgrid.mission.layout import discover_layout
from standgrid.mission.metadata import MissionMetadata, metadata_from_folder_name, read_metadata
from standgrid.mission.sensor_models import sensor_matches

#: Folders never searched for missions (ground truth of simulated missions lives in ``truth/``).
SKIPPED_FOLDERS = frozenset({"truth"})


@dataclass(frozen=True)
class MissionRecord:
    """One mission of a collection: where it is and what its metadata says."""

    path: Path
    name: str
    metadata: MissionMetadata | None
    #: Where the metadata came from: "metadata.yaml", "folder name", or None.
    metadata_source: str | None

    @property
    def date(self) -> dt.date | None:
        return _date_of(self.metadata)

    @property
    def site(self) -> str | None:
        return None if self.metadata is None else _text(_attr(self.metadata, "site", "place"))

    @property
    def robot(self) -> str | None:
        return None if self.metadata is None else _text(_attr(self.metadata, "robot", "robot_id"))

    @property
    def sensors(self) -> tuple[str, ...]:
        if self.metadata is None:
            return ()
        return tuple(str(s) for s in self.metadata.sensors)

    def to_dict(self) -> dict[str, object]:
        return {
            "name": self.name,
            "path": str(self.path),
            "date": None if self.date is None else self.date.isoformat(),
            "site": self.site,
            "robot": self.robot,
            "sensors": list(self.sensors),
            "metadata_source": self.metadata_source,
        }


def _attr(meta: object, *names: str) -> object:
    for name in names:
        value = getattr(meta, name, None)
        if value is not None:
            return value
    return None


def _text(value: object) -> str | None:
    return None if value is None else str(value)


def _date_of(meta: MissionMetadata | None) -> dt.date | None:
    if meta is None:
        return None
    value = _attr(meta, "date", "start_time", "datetime")
    if isinstance(value, dt.datetime):
        return value.date()
    if isinstance(value, dt.date):
        return value
    if isinstance(value, str):
        return dt.date.fromisoformat(value[:10])
    return None


def _as_date(value: dt.date | str | None) -> dt.date | None:
    if isinstance(value, dt.datetime):
        return value.date()
    if value is None or isinstance(value, dt.date):
        return value
    return dt.date.fromisoformat(str(value))


def _norm(text: str) -> str:
    return text.strip().lower().replace("_", "-").replace(" ", "-")


class MissionCollection:
    """The missions under ``root`` (searched up to ``max_depth`` folders deep).

    A folder is a mission when it holds a pose graph, pose table, ``metadata.yaml`` or a
    cloud folder; its sub-folders are not searched further. Metadata comes from
    ``metadata.yaml``, else from a conventional folder name. An unreadable ``metadata.yaml``
    raises with ``strict=True``; otherwise it is listed in ``problems`` and the mission kept
    with ``metadata=None``. A mission with neither is kept without metadata and noted in
    ``problems`` (in both modes).
    """

    def __init__(self, root: str | Path, *, strict: bool = False, max_depth: int = 3) -> None:
        self.root = Path(root).absolute()
        if not self.root.is_dir():
            raise MissionNotFoundError("missions folder does not exist", path=self.root)
        self.strict = strict
        self.problems: list[str] = []
        self.records: list[MissionRecord] = [
            self._record(p) for p in self._find(self.root, max_depth)
        ]
        self.records.sort(key=lambda r: (r.date or dt.date.min, r.name))

    def __len__(self) -> int:
        return len(self.records)

    def __iter__(self) -> Iterator[MissionRecord]:
        return iter(self.records)

    def _find(self, folder: Path, depth: int) -> Iterable[Path]:
        for child in sorted(folder.iterdir()):
            if not child.is_dir() or child.name.startswith(".") or child.name in SKIPPED_FOLDERS:
                continue
            if discover_layout(child).is_mission:
                yield child
            elif depth > 1:
                yield from self._find(child, depth - 1)

    def _record(self, path: Path) -> MissionRecord:
        meta_file = path / "metadata.yaml"
        if meta_file.is_file():
            try:
                return MissionRecord(path, path.name, read_metadata(meta_file), "metadata.yaml")
            except StandgridError as exc:
                if self.strict:
                    raise
                self.problems.append(str(exc))
                return MissionRecord(path, path.name, None, None)
        try:
            return MissionRecord(path, path.name, metadata_from_folder_name(path), "folder name")
        except StandgridError as exc:  # not an error: the mission simply carries no metadata
            self.problems.append(f"{path}: no metadata.yaml, and the folder name {exc.message}")
            return MissionRecord(path, path.name, None, None)

    def search(
        self,
        site: str | None = None,
        date_from: dt.date | str | None = None,
        date_to: dt.date | str | None = None,
        robot: str | None = None,
        sensors: Iterable[str] | None = None,
    ) -> list[MissionRecord]:
        """Missions matching every given criterion (dates inclusive; ``site`` and ``robot``
        case-insensitive; ``sensors``: the mission has all of them, each by name, kind or make,
        see :func:`~standgrid.mission.sensor_models.sensor_matches`: ``lidar`` finds
        ``velodyne-vlp16``). A criterion excludes missions without metadata."""
        return [
            rec
            for rec in self.records
            if metadata_matches(
                rec.site,
                rec.robot,
                rec.date,
                rec.sensors,
                site=site,
                date_from=date_from,
                date_to=date_to,
                robot=robot,
                sensors=sensors,
            )
        ]


def metadata_matches(
    mission_site: str | None,
    mission_robot: str | None,
    mission_date: dt.date | str | None,
    mission_sensors: Iterable[str],
    *,
    site: str | None = None,
    date_from: dt.date | str | None = None,
    date_to: dt.date | str | None = None,
    robot: str | None = None,
    sensors: Iterable[str] | None = None,
) -> bool:
    """Whether one mission's metadata meets every given criterion of
    :meth:`MissionCollection.search` (the one place that rule is written)."""
    start, end = _as_date(date_from), _as_date(date_to)
    date = _as_date(mission_date or None)
    wanted = [s for s in sensors if s.strip()] if sensors else []
    if site is not None and (not mission_site or _norm(mission_site) != _norm(site)):
        return False
    if robot is not None and (not mission_robot or _norm(mission_robot) != _norm(robot)):
        return False
    if start is not None and (date is None or date < start):
        return False
    if end is not None and (date is None or date > end):
        return False
    return all(sensor_matches(w, tuple(mission_sensors)) for w in wanted)
