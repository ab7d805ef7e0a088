"""A transaction: staged changes to a catalog, committed all together or not at all.

New and changed files are staged under ``.staging/<txn>/files/<relative path>`` (the new
``catalog.json`` too); the commit stages the STAC catalog of what it leaves
(:mod:`standgrid.catalog.stac`). Commit: every staged file is fsynced, then, with the readers lock
held, the journal is written and carried out (:mod:`standgrid.catalog.journal`).
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Iterable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

from standgrid._atomic import fsync_path, fsync_tree
from standgrid.catalog.journal import (
    JOURNAL_FILE,
    apply_journal,
    crash_point,
    drop_empty_staging,
    recover_locked,
    write_journal,
)
from standgrid.catalog.lock import FileLock, lock_paths, readers_excluded
from standgrid.catalog.paths import CATALOG_FILE
from standgrid.catalog.publish import note_committed
from standgrid.catalog.records import EpochRecord, MissionRecord, TilingSettings
from standgrid.catalog.state import (
    MAX_MISSION_NUMBER,
    STAGING_DIR,
    jsonable,
    read_state,
    refuse_symlinks,
    relative_path,
    utc_now,
)
from standgrid.errors import (
    CatalogConflictError,
    CatalogError,
    OutputNotWritableError,
    StandgridError,
    out_of_space_error,
)

if TYPE_CHECKING:
    from standgrid.catalog.store import Catalog


class Transaction:
    """Staged changes to a catalog, applied all together on commit (see the module doc).

    Entering takes the writer lock (unless the catalog holds it, see
    :meth:`Catalog.writing`) and reads the state under it; when the catalog changed since
    this :class:`Catalog` read it, :class:`CatalogConflictError` (the caller's reads are
    stale; nothing is lost).
    """

    def __init__(self, catalog: Catalog) -> None:
        self.catalog = catalog
        self.id = f"{datetime.now(UTC).strftime('%Y%m%dT%H%M%S')}-{uuid.uuid4().hex[:8]}"
        self.folder = catalog.root / STAGING_DIR / self.id
        self.state: dict[str, Any] = json.loads(json.dumps(catalog._state))
        self._staged: dict[str, Path] = {}
        self._deletes: set[str] = set()
        self._done = False
        self._synced = False  # the staged files were fsynced (before the readers lock)
        self._lock: FileLock | None = None

    def __enter__(self) -> Transaction:
        root = self.catalog.root
        if self.catalog._writer is None or not self.catalog._writer.held:
            self._lock = FileLock(lock_paths(self.catalog._lock_root)[0])
            self._lock.acquire(self.catalog.lock_timeout)
        try:
            # under the lock: only dead ones are left
            recover_locked(root, self.catalog._lock_root, timeout=self.catalog.lock_timeout)
            current = read_state(root / CATALOG_FILE)
            if int(current.get("generation", 0)) != self.catalog.generation or (
                current.get("updated") != self.catalog._state.get("updated")
            ):
                raise CatalogConflictError(
                    "the catalog changed since it was opened (another writer committed); "
                    "open it again and repeat",
                    path=root / CATALOG_FILE,
                )
            self.state = json.loads(json.dumps(current))
            refuse_symlinks(root, STAGING_DIR)
            (self.folder / "files").mkdir(parents=True)
        except StandgridError:  # CatalogBusyError is an OSError (TimeoutError) too
            self._release()
            raise
        except OSError as exc:
            self._release()
            raise OutputNotWritableError(f"cannot stage: {exc}", path=self.folder) from exc
        except BaseException:
            self._release()
            raise
        return self

    def _release(self) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            if exc_type is None:
                try:
                    self.commit()
                except BaseException as error:
                    self._after_failure(error)
                    raise
            else:
                assert exc is not None
                self._after_failure(exc)
        finally:
            self._release()

    def _after_failure(self, exc: BaseException) -> None:
        """Discard the staging unless the journal is written (then the next open completes
        the commit); a full disk becomes :class:`OutOfSpaceError`."""
        if not (self.folder / JOURNAL_FILE).exists():
            self.discard()
        full = out_of_space_error(exc, self.folder)
        if full is not None and full is not exc:
            raise full from exc

    # staging files

    def stage(self, relative: str | os.PathLike[str]) -> Path:
        """Where to write the new version of ``relative`` (its folder is made)."""
        rel = relative_path(relative)
        if rel == CATALOG_FILE:
            raise CatalogError("catalog.json is written by the commit itself", path=self.folder)
        target = self.folder / "files" / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        self._staged[rel] = target
        self._deletes.discard(rel)
        self._synced = False  # a file staged now is not on the disk yet
        return target

    def current(self, relative: str | os.PathLike[str]) -> Path | None:
        """The file as this transaction sees it: the staged one once written, else the catalog's."""
        rel = relative_path(relative)
        staged = self._staged.get(rel)
        if staged is not None and staged.exists():
            return staged
        if rel in self._deletes:
            return None
        path = self.catalog.root / rel
        return path if path.exists() else None

    def delete(self, relative: str | os.PathLike[str]) -> None:
        """Remove a file of the catalog on commit."""
        rel = relative_path(relative)
        self._staged.pop(rel, None)
        self._deletes.add(rel)

    # changing the catalog state

    def mission_number(self, name: str) -> int:
        """The mission's number: its existing one, or a new one never used before."""
        missions = self.state["missions"]
        if name in missions:
            return int(missions[name]["number"])
        number = int(self.state["next_mission_number"])
        if number > MAX_MISSION_NUMBER:
            raise CatalogError(
                f"no mission number left for {name!r} (LAS point_source_id is 16-bit)",
                path=self.catalog.root / CATALOG_FILE,
            )
        self.state["next_mission_number"] = number + 1
        missions[name] = {"number": number}
        return number

    def record_mission(
        self,
        name: str,
        *,
        epoch: str,
        date: str,
        path: str | os.PathLike[str] | None = None,
        georeference: Mapping[str, Any] | None = None,
        payload_count: int = 0,
        point_count: int = 0,
        tiles: Iterable[str | os.PathLike[str]] = (),
        **extra: Any,
    ) -> dict[str, Any]:
        """Set a mission's record (replacing an earlier ingest) and register its epoch."""
        number = self.mission_number(name)
        previous = self.state["missions"].get(name, {})
        old_epoch = previous.get("epoch")
        record = {
            "number": number,
            "epoch": epoch,
            "date": date,
            "path": str(path) if path is not None else None,
            "georeference": jsonable(georeference) if georeference else None,
            "payload_count": int(payload_count),
            "point_count": int(point_count),
            "tiles": sorted({relative_path(t) for t in tiles}),
            "ingested": utc_now(),
            **jsonable(extra),
        }
        self.state["missions"][name] = record
        epochs = self.state["epochs"]
        if old_epoch and old_epoch != epoch and old_epoch in epochs:
            epochs[old_epoch]["missions"] = [m for m in epochs[old_epoch]["missions"] if m != name]
            if not epochs[old_epoch]["missions"]:
                del epochs[old_epoch]
        entry = epochs.setdefault(epoch, {"date": date, "missions": []})
        entry["missions"] = sorted({*entry["missions"], name})
        return record

    # typed reads and writes of the state this transaction will commit

    def epoch_record(self, label: str) -> EpochRecord | None:
        """An epoch as this transaction has it (None: not there, or gone)."""
        entry = self.state["epochs"].get(label)
        return None if entry is None else EpochRecord.from_json(label, entry)

    def mission_records(self) -> dict[str, MissionRecord]:
        """Mission name -> its record as this transaction has it."""
        return {n: MissionRecord.from_json(n, e) for n, e in self.state["missions"].items()}

    def tiling_settings(self) -> TilingSettings:
        """How tiles were last written (0 m buffer, LAZ, not COPC if never)."""
        return TilingSettings.from_json(self.state.get("tiling"))

    def set_tiling_settings(self, settings: TilingSettings) -> None:
        """Record how this run writes tiles."""
        self.state["tiling"] = settings.to_json()

    def set_mission_tiles(self, name: str, tiles: Iterable[str]) -> None:
        """The tiles a recorded mission's points are in (after its epoch was re-tiled)."""
        self.state["missions"][name]["tiles"] = sorted({relative_path(t) for t in tiles})

    def settle_epoch(
        self, label: str, tiling: TilingSettings, *, changed: bool = True
    ) -> EpochRecord | None:
        """After tiling: the epoch's date is its missions' earliest, it is not enriched (unless
        no point ``changed``), and its tiles were written as ``tiling`` says; None when no
        mission is left."""
        entry = self.state["epochs"].get(label)
        if entry is None:
            return None
        dates = [self.state["missions"][n]["date"] for n in entry["missions"]]
        entry["date"] = min(d for d in dates if d) if any(dates) else ""
        if changed:
            entry["enriched"] = False
        entry["tiling"] = tiling.to_json()
        return EpochRecord.from_json(label, entry)

    def begin_enrichment(self, label: str) -> EpochRecord:
        """Clear an epoch's stale mark before it is enriched again; returns the epoch as it
        was (its :attr:`EpochRecord.state` says what enriching it does)."""
        entry = self.state["epochs"][label]
        before = EpochRecord.from_json(label, entry)
        entry.pop("invalidated", None)
        return before

    def mark_enriched(self, label: str, summary: Mapping[str, Any]) -> None:
        """An epoch is enriched; ``summary`` is what enrichment measured."""
        entry = self.state["epochs"][label]
        entry["enriched"] = True
        entry["enrichment"] = jsonable(dict(summary))
        entry["enrichment_id"] = uuid.uuid4().hex  # what comparisons from other catalogs read

    def record_comparison(self, key: str, entry: Mapping[str, Any]) -> None:
        """Set a comparison's record (its epochs, the other catalog, its outputs)."""
        self.state.setdefault("comparisons", {})[key] = jsonable(dict(entry))

    def remove_mission(self, name: str) -> None:
        """Drop a mission's record (its number stays reserved)."""
        record = self.state["missions"].pop(name, None)
        if record and record.get("epoch") in self.state["epochs"]:
            entry = self.state["epochs"][record["epoch"]]
            entry["missions"] = [m for m in entry["missions"] if m != name]
            if not entry["missions"]:
                del self.state["epochs"][record["epoch"]]

    # committing

    def prepare(self) -> Path:
        """Step 1 of commit: make everything durable and write the journal (from here on
        the commit will complete). Called with the readers lock held."""
        root = self.catalog.root
        missing = [rel for rel, p in self._staged.items() if not p.exists()]
        if missing:
            raise CatalogError(f"staged but never written: {missing}", path=self.folder)
        for rel in [*self._staged, *self._deletes, CATALOG_FILE]:
            refuse_symlinks(root, rel)
        self.state["updated"] = utc_now()
        self.state["generation"] = int(self.state.get("generation", 0)) + 1
        staged_state = self.folder / "files" / CATALOG_FILE
        staged_state.write_text(
            json.dumps(self.state, indent=2, sort_keys=True) + "\n", encoding="utf-8"
        )
        crash_point("staged")
        if self._synced:  # only the state is new since
            fsync_path(staged_state)
            fsync_path(staged_state.parent)
        else:
            fsync_tree(self.folder / "files")
        for rel in self._staged:  # target folders exist before the journal: renames need no space
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
        body = {
            "txn": self.id,
            "created": utc_now(),
            "generation": self.state["generation"],
            "renames": [*sorted(self._staged), CATALOG_FILE],
            "deletes": sorted(self._deletes),
        }
        path = write_journal(self.folder, body)
        crash_point("journal")
        return path

    def apply(self) -> None:
        """Step 2 of commit: carry out the journal (also what recovery does)."""
        root = self.catalog.root
        apply_journal(root, self.folder / JOURNAL_FILE)
        # every file this commit put in place is durable: publishing need not fsync them
        note_committed(root, [root / rel for rel in [*self._staged, CATALOG_FILE]])
        self.catalog.reload()
        self._done = True

    def commit(self) -> None:
        if self._done:
            return
        from standgrid.catalog.stac import stage_stac

        stage_stac(self)  # stac/ describes what this commit leaves (catalog.stac)
        # the slow part first: readers never look at the staging, so they need not wait
        # while its files reach the disk; they wait only for the journal and the renames
        fsync_tree(self.folder / "files")
        self._synced = True
        with readers_excluded(self.catalog._lock_root, self.catalog.lock_timeout):
            self.prepare()
            self.apply()

    def discard(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)
        drop_empty_staging(self.catalog.root)
        self._done = True
