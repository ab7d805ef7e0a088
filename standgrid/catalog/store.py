"""The catalog folder: ``catalog.json`` (grid, CRS, missions, epochs) and atomic updates.

Every change goes through :meth:`Catalog.transaction`::

    with Catalog.writing(path) as catalog:             # writer lock; state read under it
        with catalog.transaction() as txn:
            number = txn.mission_number(name)          # stable across re-ingests
            tile = txn.stage("tiles/2024/20m_E30734_N286855.laz")  # write the new file here
            write_tile(tile, ...)
            txn.record_mission(name, epoch="2024-05-01", tiles=[...], ...)

The rest of the catalog's machinery: :mod:`.lock` (the writer and readers locks),
:mod:`.transaction` (staging and commit), :mod:`.journal` (the commit journal and crash
recovery), :mod:`.publish` (a catalog built beside its final place), :mod:`.state`
(``catalog.json`` read and checked).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from standgrid._atomic import check_replaceable, write_text_atomic
from standgrid.catalog.journal import journals, recover_locked, roll_forward
from standgrid.catalog.lock import (
    DEFAULT_LOCK_TIMEOUT,
    FileLock,
    lock_paths,
    readers_excluded,
    writer_lock,
)
from standgrid.catalog.paths import CATALOG_FILE
from standgrid.catalog.publish import build_folder, publish, remove_stale_builds
from standgrid.catalog.records import EpochRecord, MissionRecord
from standgrid.catalog.state import (
    FORMAT_NAME,
    FORMAT_VERSION,
    SCHEMES,
    definition_dict,
    file_stamp,
    grid_fingerprint,
    is_standgrid_catalog,
    read_state,
    relative_path,
    utc_now,
)
from standgrid.catalog.transaction import Transaction
from standgrid.errors import (
    OVERWRITE_HINT,
    CatalogError,
    CatalogNotFoundError,
    EpochNotFoundError,
    GridMismatchError,
    OutputExistsError,
    OutputNotWritableError,
)


class Catalog:
    """A catalog folder. Open with :meth:`open`/:meth:`reading`/:meth:`writing`, make with
    :meth:`create`."""

    def __init__(self, root: Path, state: dict[str, Any]) -> None:
        self.root = root
        self._state = state
        #: Seconds a transaction waits for the writer lock.
        self.lock_timeout: float | None = DEFAULT_LOCK_TIMEOUT
        #: The writer lock this object's transactions use when it holds one (``writing``).
        self._writer: FileLock | None = None
        #: Where the locks are (the final place of a catalog being built beside it).
        self._lock_root: Path = root
        #: (inode, mtime ns, size) of the catalog.json ``reading`` parsed, for ``reuse``.
        self._read_from: tuple[int, int, int] | None = None

    # --- making and opening --------------------------------------------------------------

    @classmethod
    def create(
        cls,
        path: str | os.PathLike[str],
        grid_definition: Mapping[str, Any] | Any,
        crs: str,
        scheme: str = "grid",
        *,
        overwrite: bool = False,
        lock_timeout: float | None = DEFAULT_LOCK_TIMEOUT,
    ) -> Catalog:
        """Make a new, empty catalog folder (under the writer lock).

        An existing catalog or a folder with files raises :class:`OutputExistsError` unless
        ``overwrite``: then the new catalog is built beside the old one and swapped in
        atomically, so there is always a catalog at ``path``. A folder with files that is not
        a catalog is never replaced. An unwritable location raises
        :class:`OutputNotWritableError`.
        """
        if scheme not in SCHEMES:
            raise CatalogError(f"scheme must be one of {SCHEMES}, got {scheme!r}", path=path)
        root = Path(path)
        definition = definition_dict(grid_definition)
        from standgrid.partition.grid import normalise_crs

        crs = normalise_crs(crs)
        if "crs" in definition and normalise_crs(definition["crs"]) != crs:
            raise GridMismatchError(
                f"the catalog CRS {crs} differs from the grid's {definition['crs']}", path=root
            )
        if root.exists() and not root.is_dir():
            raise OutputExistsError("exists and is not a folder", path=root)
        try:
            root.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputNotWritableError(f"cannot create catalog folder: {exc}", path=root) from exc
        with writer_lock(root, timeout=lock_timeout):
            remove_stale_builds(root)
            if root.is_dir() and any(root.iterdir()):
                if not overwrite:
                    kind = "a catalog" if is_standgrid_catalog(root) else "a folder with files"
                    raise OutputExistsError(f"is {kind} ({OVERWRITE_HINT})", path=root)
                if not is_standgrid_catalog(root):  # overwriting replaces a catalog only
                    check_replaceable(root, overwrite=True, what="a catalog")
                build = build_folder(root)
                try:
                    cls._make(build, definition, crs, scheme)
                    publish(build, root, timeout=lock_timeout)
                except BaseException:
                    shutil.rmtree(build, ignore_errors=True)
                    raise
            else:
                cls._make(root, definition, crs, scheme)
        catalog = cls(root, read_state(root / CATALOG_FILE))
        catalog.lock_timeout = lock_timeout
        return catalog

    @classmethod
    def build(
        cls,
        path: str | os.PathLike[str],
        grid_definition: Mapping[str, Any] | Any,
        crs: str,
        scheme: str,
        *,
        final: str | os.PathLike[str],
        held: FileLock,
    ) -> Catalog:
        """A new catalog at ``path`` that will be published at ``final`` (:func:`publish`);
        the caller holds ``final``'s writer lock (``held``), which its transactions use."""
        if scheme not in SCHEMES:
            raise CatalogError(f"scheme must be one of {SCHEMES}, got {scheme!r}", path=final)
        from standgrid.partition.grid import normalise_crs

        root = Path(path)
        cls._make(root, definition_dict(grid_definition), normalise_crs(crs), scheme)
        catalog = cls(root, read_state(root / CATALOG_FILE))
        catalog._writer = held
        catalog._lock_root = Path(final)
        return catalog

    @classmethod
    def _make(cls, root: Path, definition: dict[str, Any], crs: str, scheme: str) -> None:
        try:
            root.mkdir(parents=True, exist_ok=True)
        except (NotADirectoryError, PermissionError, FileExistsError, OSError) as exc:
            raise OutputNotWritableError(f"cannot create catalog folder: {exc}", path=root) from exc
        if not os.access(root, os.W_OK):
            raise OutputNotWritableError("catalog folder is not writable", path=root)
        now = utc_now()
        state: dict[str, Any] = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "crs": crs,
            "scheme": scheme,
            "grid": definition,
            "fingerprint": grid_fingerprint(definition),
            "missions": {},
            "epochs": {},
            "next_mission_number": 1,
            "generation": 0,
            "created": now,
            "updated": now,
        }
        try:
            write_text_atomic(
                root / CATALOG_FILE, json.dumps(state, indent=2, sort_keys=True) + "\n"
            )
        except PermissionError as exc:
            raise OutputNotWritableError(f"cannot write catalog: {exc}", path=root) from exc

    @classmethod
    def open(
        cls, path: str | os.PathLike[str], *, lock_timeout: float | None = DEFAULT_LOCK_TIMEOUT
    ) -> Catalog:
        """Open a catalog: its state as of the last complete commit.

        A commit killed after its journal is completed first (roll forward). The files may
        change afterwards; read them inside :meth:`reading` for a consistent snapshot.
        """
        with cls.reading(path, lock_timeout=lock_timeout) as catalog:
            return catalog

    @classmethod
    @contextlib.contextmanager
    def reading(
        cls,
        path: str | os.PathLike[str],
        *,
        lock_timeout: float | None = DEFAULT_LOCK_TIMEOUT,
        reuse: Catalog | None = None,
    ) -> Iterator[Catalog]:
        """A consistent snapshot: inside the block no commit changes any file of the catalog.

        Holds the readers lock (shared; commits wait for it, writers may still stage).
        ``reuse``: a catalog an earlier ``reading`` gave; it is given again, without parsing
        catalog.json, when that file is still the one it was read from (same inode, mtime
        and size: every commit renames a new one in). Callers must treat it as read-only.
        """
        root = Path(path)
        require_catalog(root)
        readers = FileLock(lock_paths(root)[1], shared=True)
        readers.acquire(lock_timeout, what="committing to")
        try:
            if journals(root):  # a dead commit (live ones hold the readers lock): finish it
                readers.release()
                with readers_excluded(root, lock_timeout):
                    roll_forward(root)
                readers.acquire(lock_timeout, what="committing to")
            state_file = root / CATALOG_FILE
            seen = file_stamp(state_file)
            if reuse is not None and reuse.root == root and reuse._read_from == seen:
                yield reuse
            else:
                catalog = cls(root, read_state(state_file))
                catalog._read_from = seen
                yield catalog
        finally:
            readers.release()

    @classmethod
    @contextlib.contextmanager
    def writing(
        cls,
        path: str | os.PathLike[str],
        *,
        lock_timeout: float | None = DEFAULT_LOCK_TIMEOUT,
        held: FileLock | None = None,
    ) -> Iterator[Catalog]:
        """The catalog under its writer lock, interrupted work recovered, state read under
        the lock; its transactions use that lock. Raises :class:`CatalogBusyError` when
        another writer holds it for longer than ``lock_timeout`` seconds. ``held``: the
        writer lock of ``path``, already taken by the caller. A folder that is no catalog is
        refused (:class:`CatalogNotFoundError`) before any lock file is made beside it."""
        root = Path(path)
        if held is None:
            require_catalog(root)
        with (
            contextlib.nullcontext(held)
            if held
            else writer_lock(root, timeout=lock_timeout) as lock
        ):
            require_catalog(root)  # (again: it may have gone while waiting for the lock)
            recover_locked(root, timeout=lock_timeout)
            catalog = cls(root, read_state(root / CATALOG_FILE))
            catalog.lock_timeout = lock_timeout
            catalog._writer = lock
            try:
                yield catalog
            finally:
                catalog._writer = None

    @classmethod
    def open_or_create(
        cls,
        path: str | os.PathLike[str],
        grid_definition: Mapping[str, Any] | Any,
        crs: str,
        scheme: str = "grid",
    ) -> Catalog:
        """Open the catalog at ``path`` and check its grid, or create it when there is none."""
        root = Path(path)
        if (root / CATALOG_FILE).is_file():
            catalog = cls.open(root)
            catalog.check_grid(grid_definition)
            return catalog
        try:
            return cls.create(root, grid_definition, crs, scheme)
        except OutputExistsError:  # another process made it meanwhile
            catalog = cls.open(root)
            catalog.check_grid(grid_definition)
            return catalog

    # --- reading -------------------------------------------------------------------------

    @property
    def generation(self) -> int:
        """Commits since the catalog was made (changes with every commit)."""
        return int(self._state.get("generation", 0))

    @property
    def grid_definition(self) -> dict[str, Any]:
        return dict(self._state["grid"])

    @property
    def fingerprint(self) -> str:
        return str(self._state["fingerprint"])

    @property
    def crs(self) -> str:
        return str(self._state["crs"])

    @property
    def scheme(self) -> str:
        return str(self._state["scheme"])

    @property
    def missions(self) -> dict[str, dict[str, Any]]:
        """Mission name -> record (number, epoch, date, path, georeference, counts, tiles)."""
        return json.loads(json.dumps(self._state["missions"]))

    @property
    def comparisons(self) -> dict[str, dict[str, Any]]:
        """The comparisons made into this catalog (key ``<from>__<to>``)."""
        return dict(self._state.get("comparisons", {}))

    @property
    def epochs(self) -> dict[str, dict[str, Any]]:
        """Epoch label -> {"date", "missions"}."""
        return json.loads(json.dumps(self._state["epochs"]))

    @property
    def mission_records(self) -> dict[str, MissionRecord]:
        """Mission name -> its frozen record (a typed view of :attr:`missions`)."""
        return {n: MissionRecord.from_json(n, e) for n, e in self._state["missions"].items()}

    @property
    def epoch_records(self) -> dict[str, EpochRecord]:
        """Epoch label -> its frozen record (a typed view of :attr:`epochs`), in stored order."""
        return {e: EpochRecord.from_json(e, v) for e, v in self._state["epochs"].items()}

    def epoch(self, label: str) -> EpochRecord:
        """One epoch's record; :class:`EpochNotFoundError` (naming the epochs) if absent."""
        entry = self._state["epochs"].get(label)
        if entry is None:
            raise EpochNotFoundError(
                f"no epoch {label!r} (epochs: {sorted(self._state['epochs'])})",
                path=self.root / CATALOG_FILE,
            )
        return EpochRecord.from_json(label, entry)

    def mission_number(self, name: str) -> int | None:
        """The number a mission already has, or None (a transaction assigns new ones)."""
        record = self._state["missions"].get(name)
        return int(record["number"]) if record else None

    def tiles_of(self, mission: str) -> list[str]:
        """Relative paths of the tiles a mission's points are in."""
        record = self._state["missions"].get(mission)
        return list(record.get("tiles", [])) if record else []

    def tiles(self, epoch: str) -> list[str]:
        """Relative paths of every tile of an epoch."""
        if epoch not in self._state["epochs"]:
            raise EpochNotFoundError(f"no epoch {epoch!r}", path=self.root / CATALOG_FILE)
        names = self._state["epochs"][epoch]["missions"]
        return sorted({t for n in names for t in self.tiles_of(n)})

    def path(self, relative: str | os.PathLike[str]) -> Path:
        """The absolute path of a file in the catalog."""
        return self.root / relative_path(relative)

    def check_grid(self, definition: Mapping[str, Any] | Any) -> None:
        """Raise :class:`GridMismatchError` (both fingerprints named) unless the grids agree."""
        other = grid_fingerprint(definition)
        if other != self.fingerprint:
            raise GridMismatchError(
                f"grid mismatch: the catalog's grid has fingerprint {self.fingerprint}, the "
                f"given grid has {other} ({self._state['grid']} vs {definition_dict(definition)})",
                path=self.root / CATALOG_FILE,
            )

    def reload(self) -> None:
        self._state = read_state(self.root / CATALOG_FILE)

    # --- writing -------------------------------------------------------------------------

    def transaction(self) -> Transaction:
        """A new transaction over this catalog (use as a context manager)."""
        return Transaction(self)


def require_catalog(path: str | os.PathLike[str]) -> None:
    """:class:`CatalogNotFoundError` unless ``path`` holds a catalog (its ``catalog.json``):
    checked before a lock file is made beside it, so a mistaken folder gets none."""
    root = Path(path)
    if not (root / CATALOG_FILE).is_file():
        what = "does not exist" if not root.exists() else "is not a standgrid catalog"
        raise CatalogNotFoundError(f"{what} (no catalog.json)", path=root)


def open_catalog(
    path: str | os.PathLike[str], *, lock_timeout: float | None = DEFAULT_LOCK_TIMEOUT
) -> Catalog:
    """A catalog for reading, as of its last complete commit (:meth:`Catalog.open`)."""
    return Catalog.open(path, lock_timeout=lock_timeout)
