"""The catalog folder: ``catalog.json`` (grid, CRS, missions, epochs) and atomic updates.

Every change goes through :meth:`Catalog.transaction`::

    with Catalog.writing(path) as catalog:             # writer lock; state read under it
        with catalog.transaction() as txn:
            number = txn.mission_number(name)          # stable across re-ingests
            tile = txn.stage("tiles/2024/20m_E30734_N286855.laz")  # write the new file here
            write_tile(tile, ...)
            txn.record_mission(name, epoch="2024-05-01", tiles=[...], ...)

Locks (``flock``, two files *beside* the catalog folder, so they also cover creating and
replacing it): ``.<name>.lock`` is the writer lock, held by a writer from before it reads
the catalog until after it commits, so two writers never both succeed with one's work lost
(the second waits up to ``lock_timeout`` seconds, then :class:`CatalogBusyError`).
``.<name>.readers.lock`` is taken exclusively only while a commit moves files into place,
and shared by readers (:meth:`Catalog.reading`, briefly by :meth:`Catalog.open`), so a reader
holding it sees the old or the new catalog, never a mix. A writer waits for readers up to
``lock_timeout`` too (then :class:`CatalogBusyError` naming who holds the lock); every
wait longer than a second is logged (``standgrid.catalog``, INFO; the CLI prints it).

Commit: new and changed files are staged under ``.staging/<txn>/files/<relative path>``
(the new ``catalog.json`` too). Every staged file is fsynced, then the journal
``.staging/<txn>/journal.json`` (targets, deletions, generation, sha256 of its body) is
written and fsynced; then staged files are renamed into place, ``catalog.json`` last, the
folders fsynced, deletions done and the staging folder removed. A commit killed after the
journal is completed by the next writer or reader (roll forward); one killed before it, or
a torn journal (bad checksum), is discarded, leaving the previous state. Journal targets
must be plain relative paths inside the catalog whose folders are not symlinks; sources are
derived from the targets, never read from the journal. ``catalog.json`` carries a
``generation`` that every commit increments.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import re
import shutil
import time
import uuid
from collections.abc import Iterable, Iterator, Mapping
from datetime import UTC, datetime
from pathlib import Path, PurePosixPath
from types import TracebackType
from typing import Any

from standgrid._atomic import (
    FileIdentity,
    check_replaceable,
    exchange,
    file_identity,
    fsync_path,
    fsync_tree,
    temporary_sibling,
    write_text_atomic,
)
from standgrid.catalog.paths import CATALOG_FILE
from standgrid.catalog.records import EpochRecord, MissionRecord, TilingSettings
from standgrid.engine.execution import DEFAULT_LOCK_TIMEOUT  # what a writer waits: 30 s
from standgrid.errors import (
    OVERWRITE_HINT,
    CatalogBusyError,
    CatalogConflictError,
    CatalogError,
    CatalogNotFoundError,
    EpochNotFoundError,
    GridMismatchError,
    OutputExistsError,
    OutputNotWritableError,
    StandgridError,
    out_of_space_error,
)

STAGING_DIR = ".staging"
JOURNAL_FILE = "journal.json"
FORMAT_NAME = "standgrid-catalog"
FORMAT_VERSION = 1
SCHEMES = ("grid", "voronoi")
MAX_MISSION_NUMBER = 65535  # LAS point_source_id is uint16; 0 means "unknown"
#: Keys every catalog.json has.
REQUIRED_KEYS = ("format", "version", "crs", "scheme", "grid", "fingerprint", "missions",
                 "epochs", "next_mission_number")  # fmt: skip
#: Environment variable naming a commit point at which the process kills itself (crash tests).
CRASH_ENV = "STANDGRID_CRASH_AT"


def crash_point(name: str) -> None:
    """Die by SIGKILL here when ``$STANDGRID_CRASH_AT`` names this point (crash harness)."""
    wanted = os.environ.get(CRASH_ENV)
    if wanted and wanted == name:
        import signal

        os.kill(os.getpid(), signal.SIGKILL)


def _now() -> str:
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _definition_dict(definition: Mapping[str, Any] | Any) -> dict[str, Any]:
    if hasattr(definition, "to_dict"):
        definition = definition.to_dict()
    if not isinstance(definition, Mapping):
        raise CatalogError(f"grid definition must be a mapping, got {type(definition).__name__}")
    return _jsonable(dict(definition))


def _json_default(value: Any) -> Any:
    """numpy arrays and scalars, paths and tuples as JSON (fit dicts often carry numpy)."""
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def _jsonable(value: Any) -> Any:
    """A plain-JSON deep copy (raises CatalogError for values JSON cannot hold)."""
    try:
        return json.loads(json.dumps(value, sort_keys=True, default=_json_default))
    except (TypeError, ValueError) as exc:
        raise CatalogError(f"cannot store in catalog.json: {exc}") from exc


def grid_fingerprint(definition: Mapping[str, Any] | Any) -> str:
    """sha256 hex of the canonical JSON (sorted keys, no spaces) of a grid definition.

    The same text and hash as ``StandGrid.fingerprint`` for ``StandGrid.to_dict()``.
    """
    text = json.dumps(
        _definition_dict(definition), sort_keys=True, separators=(",", ":"), allow_nan=False
    )
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _relative(rel: str | os.PathLike[str]) -> str:
    """A clean relative POSIX path inside the catalog (no absolute paths, no ``..``)."""
    path = PurePosixPath(Path(rel).as_posix())
    if path.is_absolute() or ".." in path.parts or not path.parts or path.parts[0] == STAGING_DIR:
        raise CatalogError(f"not a path inside the catalog: {rel}")
    return path.as_posix()


# --- locks -------------------------------------------------------------------------------


def _absolute(path: str | os.PathLike[str]) -> Path:
    """The catalog path made absolute with symlinks resolved ("." and "x/" included)."""
    resolved = Path(os.path.realpath(os.fspath(path)))
    if not resolved.name:
        raise OutputNotWritableError("a catalog cannot be the file-system root", path=path)
    return resolved


def lock_paths(path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """The writer and the readers lock files of the catalog at ``path`` (beside it)."""
    root = _absolute(path)
    return root.parent / f".{root.name}.lock", root.parent / f".{root.name}.readers.lock"


#: Seconds a lock wait lasts before it is said (a ``standgrid.catalog`` log record).
WAIT_NOTICE_AFTER = 1.0
_log = logging.getLogger("standgrid.catalog")


def lock_holders(path: Path) -> list[str]:
    """Who holds an ``flock`` on ``path``: ``pid N: command`` per holder, from Linux's
    /proc/locks (empty where the system does not say)."""
    try:
        st = os.stat(path)
        lines = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return []
    key = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    pids = sorted(
        {int(f[4]) for f in (line.split() for line in lines)
         if len(f) > 5 and f[1] == "FLOCK" and f[5] == key and f[4].isdigit()}
    )  # fmt: skip
    holders = []
    for pid in pids:
        if pid == os.getpid():
            holders.append(f"pid {pid}: this process")
            continue
        try:
            words = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            command = " ".join(w.decode(errors="replace") for w in words if w)
        except OSError:
            command = ""
        short = command if len(command) <= 80 else command[:77] + "..."
        holders.append(f"pid {pid}: {short}" if short else f"pid {pid}")
    return holders


def _catalog_of(lock_path: Path) -> Path:
    """The catalog folder a lock file beside it is for (see :func:`lock_paths`)."""
    name = lock_path.name.removeprefix(".").removesuffix(".lock").removesuffix(".readers")
    return lock_path.parent / name


class FileLock:
    """An ``flock`` on one file, exclusive or shared, taken with a timeout."""

    def __init__(self, path: Path, *, shared: bool = False) -> None:
        self.path = path
        self.shared = shared
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self, timeout: float | None, *, what: str = "writing") -> None:
        """Take the lock, waiting up to ``timeout`` s (None: for ever), else CatalogBusyError
        naming the catalog and the processes holding the lock. A wait longer than
        :data:`WAIT_NOTICE_AFTER` is said once (log ``standgrid.catalog``, INFO)."""
        import fcntl

        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise OutputNotWritableError(f"cannot open the lock file: {exc.strerror}",
                                         path=self.path) from exc  # fmt: skip
        mode = fcntl.LOCK_SH if self.shared else fcntl.LOCK_EX
        start = time.monotonic()
        deadline = None if timeout is None else start + max(0.0, timeout)
        delay = 0.01
        said = False
        while True:
            try:
                fcntl.flock(fd, mode | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                now = time.monotonic()
                if deadline is not None and now >= deadline:
                    holders = lock_holders(self.path)
                    os.close(fd)
                    held_by = f", held by {'; '.join(holders)}" if holders else ""
                    raise CatalogBusyError(
                        f"another process is {what} this catalog (waited {timeout:g} s for "
                        f"{self.path.name}{held_by}); try again when it has finished, or "
                        "wait longer with option lock_timeout",
                        path=_catalog_of(self.path),
                        option="lock_timeout",
                    ) from None
                if not said and now - start >= WAIT_NOTICE_AFTER:
                    said = True
                    holders = lock_holders(self.path)
                    limit = "" if timeout is None else f", up to {timeout:g} s"
                    _log.info(
                        "%s: waiting for %s%s%s", _catalog_of(self.path),
                        "readers to finish" if what == "reading" else f"another process {what} it",
                        f" ({'; '.join(holders)})" if holders else "", limit,
                    )  # fmt: skip
                time.sleep(delay)
                delay = min(delay * 2, 0.2)
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing releases the flock
            self._fd = None

    def __enter__(self) -> FileLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


@contextlib.contextmanager
def writer_lock(
    path: str | os.PathLike[str], *, timeout: float | None = DEFAULT_LOCK_TIMEOUT
) -> Iterator[FileLock]:
    """Hold the writer lock of the catalog at ``path`` (which need not exist yet)."""
    lock = FileLock(lock_paths(path)[0])
    lock.acquire(timeout)
    try:
        yield lock
    finally:
        lock.release()


@contextlib.contextmanager
def _readers_excluded(
    path: str | os.PathLike[str], timeout: float | None = DEFAULT_LOCK_TIMEOUT
) -> Iterator[None]:
    """The readers lock, exclusive: while held no reader looks at the catalog. Waits up to
    ``timeout`` s for the readers there are, then :class:`CatalogBusyError`."""
    lock = FileLock(lock_paths(path)[1])
    lock.acquire(timeout, what="reading")
    try:
        yield
    finally:
        lock.release()


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
        definition = _definition_dict(grid_definition)
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
        catalog = cls(root, _read_state(root / CATALOG_FILE))
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
        cls._make(root, _definition_dict(grid_definition), normalise_crs(crs), scheme)
        catalog = cls(root, _read_state(root / CATALOG_FILE))
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
        now = _now()
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
            if _journals(root):  # a dead commit (live ones hold the readers lock): finish it
                readers.release()
                with _readers_excluded(root, lock_timeout):
                    _roll_forward(root)
                readers.acquire(lock_timeout, what="committing to")
            state_file = root / CATALOG_FILE
            seen = _file_identity(state_file)
            if reuse is not None and reuse.root == root and reuse._read_from == seen:
                yield reuse
            else:
                catalog = cls(root, _read_state(state_file))
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
            _recover(root, timeout=lock_timeout)
            catalog = cls(root, _read_state(root / CATALOG_FILE))
            catalog.lock_timeout = lock_timeout
            catalog._writer = lock
            try:
                yield catalog
            finally:
                catalog._writer = None

    @classmethod
    def open_or_create(
        cls, path: str | os.PathLike[str], grid_definition: Mapping[str, Any] | Any, crs: str,
        scheme: str = "grid",
    ) -> Catalog:  # fmt: skip
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
        return self.root / _relative(relative)

    def check_grid(self, definition: Mapping[str, Any] | Any) -> None:
        """Raise :class:`GridMismatchError` (both fingerprints named) unless the grids agree."""
        other = grid_fingerprint(definition)
        if other != self.fingerprint:
            raise GridMismatchError(
                f"grid mismatch: the catalog's grid has fingerprint {self.fingerprint}, the "
                f"given grid has {other} ({self._state['grid']} vs {_definition_dict(definition)})",
                path=self.root / CATALOG_FILE,
            )

    def reload(self) -> None:
        self._state = _read_state(self.root / CATALOG_FILE)

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


class Transaction:
    """Staged changes to a catalog, applied all together on commit (see module doc).

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
            _recover(root, self.catalog._lock_root, timeout=self.catalog.lock_timeout)
            current = _read_state(root / CATALOG_FILE)
            if int(current.get("generation", 0)) != self.catalog.generation or (
                current.get("updated") != self.catalog._state.get("updated")
            ):
                raise CatalogConflictError(
                    "the catalog changed since it was opened (another writer committed); "
                    "open it again and repeat",
                    path=root / CATALOG_FILE,
                )
            self.state = json.loads(json.dumps(current))
            _refuse_symlinks(root, STAGING_DIR)
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
        rel = _relative(relative)
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
        rel = _relative(relative)
        staged = self._staged.get(rel)
        if staged is not None and staged.exists():
            return staged
        if rel in self._deletes:
            return None
        path = self.catalog.root / rel
        return path if path.exists() else None

    def delete(self, relative: str | os.PathLike[str]) -> None:
        """Remove a file of the catalog on commit."""
        rel = _relative(relative)
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
            "georeference": _jsonable(georeference) if georeference else None,
            "payload_count": int(payload_count),
            "point_count": int(point_count),
            "tiles": sorted({_relative(t) for t in tiles}),
            "ingested": _now(),
            **_jsonable(extra),
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
        self.state["missions"][name]["tiles"] = sorted({_relative(t) for t in tiles})

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
        entry["enrichment"] = _jsonable(dict(summary))
        entry["enrichment_id"] = uuid.uuid4().hex  # what comparisons from other catalogs read

    def record_comparison(self, key: str, entry: Mapping[str, Any]) -> None:
        """Set a comparison's record (its epochs, the other catalog, its outputs)."""
        self.state.setdefault("comparisons", {})[key] = _jsonable(dict(entry))

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
            _refuse_symlinks(root, rel)
        self.state["updated"] = _now()
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
            "created": _now(),
            "generation": self.state["generation"],
            "renames": [*sorted(self._staged), CATALOG_FILE],
            "deletes": sorted(self._deletes),
        }
        path = self.folder / JOURNAL_FILE
        # durable: the journal's data, then its folder (the one fsync that makes it count)
        write_text_atomic(path, json.dumps({"journal": body, "sha256": _digest(body)}) + "\n")
        crash_point("journal")
        return path

    def apply(self) -> None:
        """Step 2 of commit: carry out the journal (also what recovery does)."""
        root = self.catalog.root
        apply_journal(root, self.folder / JOURNAL_FILE)
        # every file this commit put in place is durable (data fsynced before the journal,
        # folders after the renames): publishing a catalog built here need not fsync them
        placed = (file_identity(root / rel) for rel in [*self._staged, CATALOG_FILE])
        _COMMITTED[os.path.realpath(root)] = {ident for ident in placed if ident is not None}
        while len(_COMMITTED) > _COMMITTED_ROOTS:  # a long-lived process: the latest only
            del _COMMITTED[next(iter(_COMMITTED))]
        self.catalog.reload()
        self._done = True

    def commit(self) -> None:
        if self._done:
            return
        # the slow part first: readers never look at the staging, so they need not wait
        # while its files reach the disk; they wait only for the journal and the renames
        fsync_tree(self.folder / "files")
        self._synced = True
        with _readers_excluded(self.catalog._lock_root, self.catalog.lock_timeout):
            self.prepare()
            self.apply()

    def discard(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)
        _drop_empty_staging(self.catalog.root)
        self._done = True


# --- reading and checking state -----------------------------------------------------------


def is_standgrid_catalog(root: Path) -> bool:
    """True when ``root/catalog.json`` is a standgrid catalog's (its ``format``); another
    tool's catalog.json (a STAC catalog) is not."""
    try:
        with open(root / CATALOG_FILE, encoding="utf-8") as stream:
            state = json.load(stream)
    except (OSError, ValueError):
        return False
    return isinstance(state, dict) and state.get("format") == FORMAT_NAME


def _read_state(path: Path) -> dict[str, Any]:
    try:
        state = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise CatalogError(
            f"malformed catalog.json: {exc.msg}", path=path, line=exc.lineno
        ) from exc
    except UnicodeDecodeError as exc:
        raise CatalogError(f"catalog.json is not UTF-8 text ({exc.reason})", path=path) from exc
    except OSError as exc:
        raise CatalogNotFoundError(f"cannot read catalog.json: {exc}", path=path) from exc
    if not isinstance(state, dict) or state.get("format") != FORMAT_NAME:
        raise CatalogNotFoundError("catalog.json is not a standgrid catalog", path=path)
    missing = [key for key in REQUIRED_KEYS if key not in state]
    if missing:
        raise CatalogError(f"catalog.json lacks {', '.join(missing)}", path=path)
    for key in ("missions", "epochs", "grid"):
        if not isinstance(state[key], dict):
            raise CatalogError(f"catalog.json: {key!r} is not an object", path=path)
    for name, record in state["missions"].items():
        if not isinstance(record, dict) or not isinstance(record.get("number"), int):
            raise CatalogError(f"catalog.json: mission {name!r} has no number", path=path)
    for epoch, entry in state["epochs"].items():
        if not isinstance(entry, dict) or not isinstance(entry.get("missions"), list):
            raise CatalogError(f"catalog.json: epoch {epoch!r} has no mission list", path=path)
    try:
        expected = grid_fingerprint(state["grid"])
    except StandgridError as exc:
        raise CatalogError(f"catalog.json: unusable grid ({exc.message})", path=path) from exc
    if state["fingerprint"] != expected:
        raise CatalogError(
            f"catalog.json: the stored fingerprint {state['fingerprint']} does not match its "
            f"grid (which has {expected}); the file was edited by hand",
            path=path,
        )
    return state


def _file_identity(path: Path) -> tuple[int, int, int] | None:
    try:
        stat = path.stat()
    except OSError:
        return None
    return (stat.st_ino, stat.st_mtime_ns, stat.st_size)


def _refuse_symlinks(root: Path, rel: str) -> None:
    """Refuse a catalog path whose folders inside the catalog are symlinks (writes through a
    symlink would land outside the catalog)."""
    current = root
    parts = PurePosixPath(rel).parts
    for index, part in enumerate(parts):
        current = current / part
        if current.is_symlink() and (index < len(parts) - 1 or part == STAGING_DIR):
            raise CatalogError(
                f"{PurePosixPath(*parts[: index + 1])} is a symlink; the catalog does not write "
                "through symlinks",
                path=current,
            )
        if not current.exists():
            return


def _digest(body: Mapping[str, Any]) -> str:
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode("utf-8")).hexdigest()


def _read_journal(journal_path: Path) -> dict[str, Any] | None:
    """The journal's body, or None when it is torn, empty or fails its checksum."""
    try:
        data = json.loads(journal_path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError, OSError):
        return None
    if not isinstance(data, dict) or not isinstance(data.get("journal"), dict):
        return None
    body = data["journal"]
    if data.get("sha256") != _digest(body):
        return None
    return body


def _journal_targets(
    root: Path, body: Mapping[str, Any], journal_path: Path
) -> tuple[list[str], list[str]]:
    """Checked targets and deletions: relative paths inside the catalog, no symlinked folders."""
    renames, deletes = body.get("renames"), body.get("deletes")
    if not isinstance(renames, list) or not isinstance(deletes, list):
        raise CatalogError("journal lists no renames/deletes", path=journal_path)
    checked = []
    for item in [*renames, *deletes]:
        if not isinstance(item, str):
            raise CatalogError(f"journal entry {item!r} is not a path", path=journal_path)
        try:
            rel = _relative(item)
        except CatalogError as exc:
            raise CatalogError(f"journal path escapes the catalog: {item!r}",
                               path=journal_path) from exc  # fmt: skip
        _refuse_symlinks(root, rel)
        checked.append(rel)
    return checked[: len(renames)], checked[len(renames) :]


def apply_journal(root: Path, journal_path: Path) -> None:
    """Rename staged files into place (catalog.json last), fsync, delete, drop the staging.

    Sources are ``<journal folder>/files/<target>``, never taken from the journal.
    Idempotent: a rename already done (staged file gone, target present) is skipped. A torn
    journal raises :class:`CatalogError` (recovery discards it instead).
    """
    body = _read_journal(journal_path)
    if body is None:
        raise CatalogError("torn or tampered journal (checksum mismatch)", path=journal_path)
    renames, deletes = _journal_targets(root, body, journal_path)
    if _is_superseded(root, body):  # replaying its deletes would hit newer files
        shutil.rmtree(journal_path.parent, ignore_errors=True)
        fsync_path(journal_path.parent.parent)
        return
    files = journal_path.parent / "files"
    if (files / CATALOG_FILE).exists():
        _read_state(files / CATALOG_FILE)  # a journal never installs a broken catalog.json
    folders: set[Path] = set()
    synced: set[Path] = set()  # folders fsynced since their last rename
    for number, rel in enumerate(renames):
        src, dst = files / rel, root / rel
        if src.is_symlink():
            raise CatalogError("a staged file is a symlink", path=src)
        if src.exists():
            dst.parent.mkdir(parents=True, exist_ok=True)
            if rel == CATALOG_FILE:
                for folder in sorted(folders):
                    fsync_path(folder)
                synced |= folders
                crash_point("before-catalog-json")
            os.replace(src, dst)
            folders.add(dst.parent)
            synced.discard(dst.parent)
            crash_point(f"rename-{number}")
        elif not dst.exists():
            raise CatalogError(
                f"staged file {src.relative_to(root)} and its target {rel} are both missing",
                path=journal_path,
            )
    for folder in sorted(folders - synced):  # each folder once: the renames are durable
        fsync_path(folder)
    for rel in deletes:
        (root / rel).unlink(missing_ok=True)
    for folder in sorted({(root / rel).parent for rel in deletes}):
        if folder.is_dir():  # each unlink is durable, not only the catalog root's
            fsync_path(folder)
    crash_point("applied")
    shutil.rmtree(journal_path.parent, ignore_errors=True)
    fsync_path(journal_path.parent.parent)  # a finished journal does not come back
    _drop_empty_staging(root)


def _is_superseded(root: Path, body: Mapping[str, Any]) -> bool:
    """A journal older than the catalog's state: a later commit already happened (the
    journal survived its own removal, e.g. a power loss before that was on disk)."""
    current = root / CATALOG_FILE
    if not current.is_file():
        return False
    try:
        generation = int(json.loads(current.read_text(encoding="utf-8")).get("generation", 0))
        return int(body.get("generation", 0)) < generation
    except (ValueError, TypeError, OSError, AttributeError):
        return False  # an unreadable catalog.json: leave the decision to the journal


def _drop_empty_staging(root: Path) -> None:
    with contextlib.suppress(OSError):  # not empty (another transaction) or already gone
        (root / STAGING_DIR).rmdir()


def _staging_folders(root: Path) -> Iterator[Path]:
    staging = root / STAGING_DIR
    if staging.is_dir() and not staging.is_symlink():
        yield from sorted(p for p in staging.iterdir() if p.is_dir() and not p.is_symlink())


def _journals(root: Path) -> list[Path]:
    return [f / JOURNAL_FILE for f in _staging_folders(root) if (f / JOURNAL_FILE).is_file()]


def _roll_forward(root: Path) -> list[str]:
    """Complete every journaled (dead) commit; torn journals are discarded. Needs the readers
    lock exclusively."""
    done = []
    for journal in _journals(root):
        if _read_journal(journal) is None:
            shutil.rmtree(journal.parent, ignore_errors=True)
            done.append(f"discarded {journal.parent.name} (torn journal)")
            continue
        apply_journal(root, journal)
        done.append(f"completed {journal.parent.name}")
    _drop_empty_staging(root)
    return done


def recover(root: str | os.PathLike[str]) -> list[str]:
    """Complete journaled transactions, discard unjournaled ones; returns what was done.

    Does nothing while another process holds the writer lock (its staging is live).
    """
    base = Path(root)
    try:
        with writer_lock(base, timeout=0):
            return _recover(base)
    except CatalogBusyError:
        return []


_TMP_NAME = re.compile(r"^\.(?P<name>.+)\.(?:[a-z]+-)?(?P<pid>\d+)(?:-[0-9a-f]+)?\.tmp$")


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _recover(
    base: Path, lock_root: Path | None = None, *, timeout: float | None = DEFAULT_LOCK_TIMEOUT
) -> list[str]:
    """Under the writer lock: finish dead commits, drop dead staging and temporary files
    (waiting up to ``timeout`` s for the readers there are)."""
    with _readers_excluded(lock_root or base, timeout):
        done = _roll_forward(base)
    for folder in _staging_folders(base):  # no journal: a dead writer's half-staged work
        shutil.rmtree(folder, ignore_errors=True)
        done.append(f"discarded {folder.name}")
    _drop_empty_staging(base)
    if base.is_dir():
        for leftover in base.iterdir():  # .catalog.json.<pid>-<id>.tmp of a killed write
            match = _TMP_NAME.match(leftover.name)
            if match and leftover.is_file() and not _pid_alive(int(match["pid"])):
                leftover.unlink(missing_ok=True)
                done.append(f"removed {leftover.name}")
    return done


# --- building a catalog beside its final place ---------------------------------------------


#: Catalog folder (real path) -> identities of the files the last commit in this process
#: made durable there (:meth:`Transaction.apply`); :func:`publish` fsyncs only the others.
_COMMITTED: dict[str, set[FileIdentity]] = {}
_COMMITTED_ROOTS = 8


def build_folder(final: Path) -> Path:
    """A fresh hidden sibling to build a catalog in (``.<name>.build-<pid>-<id>.tmp``)."""
    return temporary_sibling(_absolute(final).parent / Path(final).name, "build")


def publish(build: Path, final: Path, *, timeout: float | None = DEFAULT_LOCK_TIMEOUT) -> None:
    """Put the catalog built at ``build`` at ``final``, atomically for readers (call under
    the writer lock). An existing ``final`` is exchanged with it (``renameat2``), so there
    is a catalog at ``final`` at every moment; where the system cannot exchange, the old one
    is moved aside as ``.<name>.old-<pid>-<id>.tmp`` first, and put back by
    :func:`remove_stale_builds` if the process dies before the new one is in place. Waits up
    to ``timeout`` s for the catalog's readers, then :class:`CatalogBusyError`.

    Every file of ``build`` is fsynced first, but those its last commit in this process put
    in place, unchanged since (their data and folders were fsynced by that commit: each
    file's data reaches the disk once); every folder is fsynced."""
    fsync_tree(build, durable=_COMMITTED.pop(os.path.realpath(build), ()))
    with _readers_excluded(final, timeout):
        crash_point("publish")
        if not final.exists():
            os.rename(build, final)
        elif exchange(build, final):
            crash_point("exchanged")
        else:
            old = temporary_sibling(final, "old")
            os.rename(final, old)
            crash_point("moved-aside")
            os.rename(build, final)
            build = old
        fsync_path(final.parent)
    shutil.rmtree(build, ignore_errors=True)  # the old catalog, now replaced


def remove_stale_builds(final: str | os.PathLike[str]) -> list[str]:
    """Under the writer lock: tidy the siblings killed builds left beside a catalog.

    A catalog moved aside by an interrupted overwrite (``.old-``) is put back when there is
    no catalog at ``final``; nothing holding a catalog.json is deleted unless ``final`` is a
    complete catalog. Half-built folders of dead processes are removed.
    """
    path = Path(final)
    parent = path.parent
    done: list[str] = []
    if not parent.is_dir():
        return done
    pattern = re.compile(rf"^\.{re.escape(path.name)}\.(?:(build|old)-)?(\d+)-[0-9a-f]+\.tmp$")
    siblings = []
    for sibling in parent.iterdir():
        match = pattern.match(sibling.name)
        if (
            match
            and sibling.is_dir()
            and not sibling.is_symlink()
            and not _pid_alive(int(match[2]))
        ):
            siblings.append((match[1] or "", sibling))
    complete = (path / CATALOG_FILE).is_file()
    if not complete:
        olds = sorted((s for kind, s in siblings if kind == "old" and (s / CATALOG_FILE).is_file()),
                      key=lambda s: s.stat().st_mtime)  # fmt: skip
        if olds:
            if path.exists():
                with contextlib.suppress(OSError):
                    path.rmdir()  # an empty folder only
            os.rename(olds[-1], path)
            fsync_path(parent)
            done.append(f"restored {olds[-1].name}")
            complete = True
            siblings = [(k, s) for k, s in siblings if s != olds[-1]]
    for kind, sibling in siblings:
        if (sibling / CATALOG_FILE).is_file() and not complete and kind != "build":
            continue  # maybe the only copy of a catalog: never deleted
        shutil.rmtree(sibling, ignore_errors=True)
        done.append(f"removed {sibling.name}")
    return done
