"""The catalog folder: ``catalog.json`` (grid, CRS, missions, epochs) and atomic updates.

Every change goes through :meth:`Catalog.transaction`::

    with catalog.transaction() as txn:
        number = txn.mission_number(name)              # stable across re-ingests
        tile = txn.stage("tiles/2024/20m_E30734_N286855.laz")  # write the new file here
        write_tile(tile, ...)
        txn.record_mission(name, epoch="2024-05-01", tiles=[...], ...)

New and changed files are written under ``.staging/<txn-id>/files/<relative path>``. Commit
writes ``.staging/<txn-id>/journal.json`` (the renames, deletions and the new catalog
state), renames each staged file into place, writes ``catalog.json`` atomically and deletes
the staging folder. :meth:`Catalog.open` completes a transaction whose journal exists (roll
forward) and discards one without a journal, so readers always see a consistent catalog.
One writer at a time: a catalog is not locked against concurrent writers.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import uuid
from collections.abc import Iterable, Iterator, Mapping
from datetime import UTC, datetime
from pathlib import Path, PurePosixPath
from types import TracebackType
from typing import Any

from standgrid._atomic import write_text_atomic
from standgrid.errors import (
    CatalogError,
    CatalogNotFoundError,
    EpochNotFoundError,
    GridMismatchError,
    OutputExistsError,
    OutputNotWritableError,
)

CATALOG_FILE = "catalog.json"
STAGING_DIR = ".staging"
JOURNAL_FILE = "journal.json"
FORMAT_NAME = "standgrid-catalog"
FORMAT_VERSION = 1
SCHEMES = ("grid", "voronoi")
MAX_MISSION_NUMBER = 65535  # LAS point_source_id is uint16; 0 means "unknown"


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


class Catalog:
    """A catalog folder. Open with :meth:`open`, make with :meth:`create`."""

    def __init__(self, root: Path, state: dict[str, Any]) -> None:
        self.root = root
        self._state = state

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
    ) -> Catalog:
        """Make a new, empty catalog folder.

        An existing catalog or a folder with files raises :class:`OutputExistsError` unless
        ``overwrite`` (which empties the folder). An unwritable location raises
        :class:`OutputNotWritableError`.
        """
        if scheme not in SCHEMES:
            raise CatalogError(f"scheme must be one of {SCHEMES}, got {scheme!r}", path=path)
        root = Path(path)
        if root.exists() and not root.is_dir():
            raise OutputExistsError("exists and is not a folder", path=root)
        if root.is_dir() and any(root.iterdir()):
            if not overwrite:
                kind = "a catalog" if (root / CATALOG_FILE).is_file() else "a folder with files"
                raise OutputExistsError(f"is {kind} (use overwrite to replace it)", path=root)
            shutil.rmtree(root)
        try:
            root.mkdir(parents=True, exist_ok=True)
        except (NotADirectoryError, PermissionError, FileExistsError, OSError) as exc:
            raise OutputNotWritableError(f"cannot create catalog folder: {exc}", path=root) from exc
        if not os.access(root, os.W_OK):
            raise OutputNotWritableError("catalog folder is not writable", path=root)
        definition = _definition_dict(grid_definition)
        from standgrid.partition.grid import normalise_crs

        crs = normalise_crs(crs)
        if "crs" in definition and normalise_crs(definition["crs"]) != crs:
            raise GridMismatchError(
                f"the catalog CRS {crs} differs from the grid's {definition['crs']}", path=root
            )
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
            "created": now,
            "updated": now,
        }
        try:
            write_text_atomic(
                root / CATALOG_FILE, json.dumps(state, indent=2, sort_keys=True) + "\n"
            )
        except PermissionError as exc:
            raise OutputNotWritableError(f"cannot write catalog: {exc}", path=root) from exc
        return cls(root, state)

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> Catalog:
        """Open a catalog, first completing or discarding interrupted transactions."""
        root = Path(path)
        if not (root / CATALOG_FILE).is_file():
            raise CatalogNotFoundError("not a standgrid catalog (no catalog.json)", path=root)
        recover(root)
        return cls(root, _read_state(root / CATALOG_FILE))

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
        return cls.create(root, grid_definition, crs, scheme)

    # --- reading -------------------------------------------------------------------------

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
    def epochs(self) -> dict[str, dict[str, Any]]:
        """Epoch label -> {"date", "missions"}."""
        return json.loads(json.dumps(self._state["epochs"]))

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


class Transaction:
    """Staged changes to a catalog, applied all together on commit (see module doc)."""

    def __init__(self, catalog: Catalog) -> None:
        self.catalog = catalog
        self.id = f"{datetime.now(UTC).strftime('%Y%m%dT%H%M%S')}-{uuid.uuid4().hex[:8]}"
        self.folder = catalog.root / STAGING_DIR / self.id
        self.state: dict[str, Any] = json.loads(json.dumps(catalog._state))
        self._staged: dict[str, Path] = {}
        self._deletes: set[str] = set()
        self._done = False

    def __enter__(self) -> Transaction:
        self._lock = writer_lock(self.catalog.root)
        if not self._lock.__enter__():
            self._lock.__exit__(None, None, None)
            raise CatalogError(
                "another process is writing this catalog; try again when it has finished",
                path=self.catalog.root,
            )
        try:
            _recover(self.catalog.root)  # under the lock: only dead transactions are left
            (self.folder / "files").mkdir(parents=True)
        except OSError as exc:
            self._lock.__exit__(None, None, None)
            raise OutputNotWritableError(f"cannot stage: {exc}", path=self.folder) from exc
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            if exc_type is None:
                self.commit()
            elif not (self.folder / JOURNAL_FILE).exists():
                self.discard()
            # with a journal written, the next Catalog.open() completes the commit
        finally:
            self._lock.__exit__(None, None, None)

    # staging files

    def stage(self, relative: str | os.PathLike[str]) -> Path:
        """Where to write the new version of ``relative`` (its folder is made)."""
        rel = _relative(relative)
        target = self.folder / "files" / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        self._staged[rel] = target
        self._deletes.discard(rel)
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
        """Step 1 of commit: write the journal. From here on the commit will complete."""
        missing = [rel for rel, p in self._staged.items() if not p.exists()]
        if missing:
            raise CatalogError(f"staged but never written: {missing}", path=self.folder)
        self.state["updated"] = _now()
        journal = {
            "txn": self.id,
            "created": _now(),
            "renames": [
                [(self.folder / "files" / rel).relative_to(self.catalog.root).as_posix(), rel]
                for rel in sorted(self._staged)
            ],
            "deletes": sorted(self._deletes),
            "catalog": self.state,
        }
        path = self.folder / JOURNAL_FILE
        write_text_atomic(path, json.dumps(journal, indent=2, sort_keys=True) + "\n")
        return path

    def apply(self) -> None:
        """Step 2 of commit: carry out the journal (also what recovery does)."""
        apply_journal(self.catalog.root, self.folder / JOURNAL_FILE)
        self.catalog.reload()
        self._done = True

    def commit(self) -> None:
        if self._done:
            return
        self.prepare()
        self.apply()

    def discard(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)
        _drop_empty_staging(self.catalog.root)
        self._done = True


# --- journal handling (module level so recovery needs no Transaction) -------------------


def _read_state(path: Path) -> dict[str, Any]:
    try:
        state = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise CatalogError(
            f"malformed catalog.json: {exc.msg}", path=path, line=exc.lineno
        ) from exc
    except OSError as exc:
        raise CatalogNotFoundError(f"cannot read catalog.json: {exc}", path=path) from exc
    if not isinstance(state, dict) or state.get("format") != FORMAT_NAME:
        raise CatalogNotFoundError("catalog.json is not a standgrid catalog", path=path)
    return state


def apply_journal(root: Path, journal_path: Path) -> None:
    """Rename staged files into place, delete, write catalog.json, drop the staging folder.

    Idempotent: a rename already done (staged file gone, target present) is skipped.
    """
    try:
        journal = json.loads(journal_path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise CatalogError(
            f"malformed journal: {exc.msg}", path=journal_path, line=exc.lineno
        ) from exc
    for source, target in journal["renames"]:
        src, dst = root / source, root / _relative(target)
        if src.exists():
            dst.parent.mkdir(parents=True, exist_ok=True)
            os.replace(src, dst)
        elif not dst.exists():
            raise CatalogError(f"staged file {source} and its target {target} are both missing",
                               path=journal_path)  # fmt: skip
    for rel in journal["deletes"]:
        (root / _relative(rel)).unlink(missing_ok=True)
    write_text_atomic(
        root / CATALOG_FILE, json.dumps(journal["catalog"], indent=2, sort_keys=True) + "\n"
    )
    shutil.rmtree(journal_path.parent, ignore_errors=True)
    _drop_empty_staging(root)


def _drop_empty_staging(root: Path) -> None:
    with contextlib.suppress(OSError):  # not empty (another transaction) or already gone
        (root / STAGING_DIR).rmdir()


def _staging_folders(root: Path) -> Iterator[Path]:
    staging = root / STAGING_DIR
    if staging.is_dir():
        yield from sorted(p for p in staging.iterdir() if p.is_dir())


LOCK_FILE = ".lock"


@contextlib.contextmanager
def writer_lock(root: Path, *, wait: bool = False) -> Iterator[bool]:
    """An exclusive advisory lock (``flock``) on the catalog; yields whether it was taken.

    Transactions hold it from staging to commit, so one writer at a time works on a catalog
    and recovery never discards another process's live staging folder.
    """
    import fcntl

    fd = os.open(root / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
            taken = True
        except BlockingIOError:
            taken = False
        yield taken
    finally:
        os.close(fd)  # closing releases the lock


def recover(root: str | os.PathLike[str]) -> list[str]:
    """Complete journaled transactions, discard unjournaled ones; returns what was done.

    Does nothing while another process holds the writer lock (its staging is live).
    """
    base = Path(root)
    with writer_lock(base) as taken:
        return _recover(base) if taken else []


def _recover(base: Path) -> list[str]:
    done = []
    for folder in _staging_folders(base):
        journal = folder / JOURNAL_FILE
        if journal.is_file():
            apply_journal(base, journal)
            done.append(f"completed {folder.name}")
        else:
            shutil.rmtree(folder, ignore_errors=True)
            done.append(f"discarded {folder.name}")
    _drop_empty_staging(base)
    return done
