"""A catalog in object storage: whole catalog generations, switched by one pointer object.

Under the catalog's URL (``s3://bucket/prefix``)::

    _standgrid/HEAD.json             the pointer: {"generation": 12, "root": "g000012-ab12cd34"}
    _standgrid/lock.json             the writer's lease (created only where absent)
    _standgrid/manifests/<root>.json every file of a generation: size and SHA-256
    g000012-ab12cd34/…               generation 12: a complete catalog folder (catalog.json,
                                     index.gpkg, tiles/, rasters, tables, VPCs, QGIS project)

A stage works on a local working copy of the generation HEAD names (:func:`catalog_at`),
with every guarantee of a catalog on disk. Its commit writes a new generation beside the
old one: changed and new files are uploaded (multipart when large), unchanged ones copied
inside the store, then the manifest, then HEAD is switched with a conditional write
(``If-Match`` its ETag, or ``If-None-Match`` for the first). That switch is the commit:
a reader (``status``, ``serve``, a working copy) reads HEAD, then the generation it names,
so it sees the old catalog until the switch and the new one after, never a mix; a writer
killed at any moment leaves HEAD on the old generation (the half-written one is removed by
the next commit). Two writers: the lease keeps the second waiting; should the lease be lost,
the conditional switch refuses the second commit (:class:`CatalogConflictError`).

The previous generation is kept for readers still reading it; older ones are deleted after
the switch. Plain HTTP clients find the current one through ``_standgrid/HEAD.json``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import shutil
import socket
import tempfile
import threading
import time
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from standgrid.catalog.journal import crash_point, pid_alive
from standgrid.catalog.paths import CATALOG_FILE
from standgrid.catalog.state import STAGING_DIR
from standgrid.errors import (
    CatalogBusyError,
    CatalogConflictError,
    CatalogNotFoundError,
    StandgridError,
    StorageError,
)
from standgrid.storage.objects import (
    ObjectFolder,
    PreconditionFailed,
    copy_many,
    file_sha256,
    is_url,
    mirror_down,
    mirror_up,
)

HEAD = "_standgrid/HEAD.json"
LOCK = "_standgrid/lock.json"
MANIFESTS = "_standgrid/manifests"
_log = logging.getLogger("standgrid.catalog")
#: A generation's folder name (nothing else at the catalog's URL is ever deleted).
_GENERATION = re.compile(r"^g\d{6}-[0-9a-f]{8}$")
#: Where workers without a shared folder put what they write (:func:`outbox_url`).
OUTBOX = "_standgrid/outbox"
FORMAT = 1
#: Seconds a writer's lease lasts without renewal (renewed every third of it).
LEASE_SECONDS = 60.0
#: Where working copies and fetched missions go (default: the system's temporary folder).
WORK_ENV = "STANDGRID_WORK_DIR"


#: Files workers already put in object storage (SHA-256 -> URL), for the next commit to copy
#: inside the store rather than upload again (:func:`note_in_store`).
_IN_STORE: dict[str, str] = {}


#: Working copies checked out in this process: real path -> their generation's URL and
#: manifest (relative path -> size and sha256).
_CHECKOUTS: dict[str, tuple[str, dict[str, dict[str, Any]]]] = {}


def generation_of(root: str | os.PathLike[str]) -> tuple[str, dict[str, dict[str, Any]]] | None:
    """The URL and manifest of the generation the working copy at ``root`` holds (None:
    ``root`` is no working copy, or of a new catalog)."""
    return _CHECKOUTS.get(os.path.realpath(root))


def note_in_store(url: str, sha256: str) -> None:
    """A file with this digest is in the store at ``url`` (a worker put it there)."""
    _IN_STORE[sha256] = url


@dataclass(frozen=True)
class Head:
    """What HEAD names, and its ETag (None: no catalog yet)."""

    generation: int
    root: str
    etag: str | None


def _work_folder(prefix: str) -> Path:
    base = os.environ.get(WORK_ENV) or None
    if base:
        Path(base).mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=prefix, dir=base))


class Lease:
    """The writer's lease on ``_standgrid/lock.json``: taken by a create-only write, renewed
    by conditional writes from a thread, given up by deleting it. A lease past its time, or
    held by a dead process of this host, is taken over."""

    def __init__(self, folder: ObjectFolder, timeout: float | None) -> None:
        self.folder = folder
        self.timeout = timeout
        self.owner = uuid.uuid4().hex
        self.etag: str | None = None
        self.lost = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _body(self) -> bytes:
        return json.dumps(
            {
                "owner": self.owner,
                "host": socket.gethostname(),
                "pid": os.getpid(),
                "expires": time.time() + LEASE_SECONDS,
            }
        ).encode()

    @staticmethod
    def _expires(held: dict[str, Any]) -> float:
        try:
            return float(held.get("expires", 0))
        except (TypeError, ValueError):
            return 0.0  # not a lease this code wrote: takeable

    def _takeable(self, held: dict[str, Any]) -> bool:
        if self._expires(held) < time.time():
            return True
        pid = held.get("pid")
        return (
            held.get("host") == socket.gethostname()
            and isinstance(pid, int)
            and (not pid_alive(pid))
        )

    def acquire(self) -> Lease:
        deadline = None if self.timeout is None else time.monotonic() + self.timeout
        while True:
            try:
                self.etag = self.folder.write(LOCK, self._body(), create=True)
                break
            except PreconditionFailed:
                pass
            found = self.folder.read(LOCK)
            if found is not None:
                try:
                    held = json.loads(found[0])
                except ValueError:
                    held = {}
                held = held if isinstance(held, dict) else {}
                if self._takeable(held):
                    with contextlib.suppress(PreconditionFailed):
                        self.etag = self.folder.write(LOCK, self._body(), if_match=found[1])
                        break
                elif deadline is not None and time.monotonic() >= deadline:
                    raise CatalogBusyError(
                        f"{self.folder.url}: another writer holds the catalog (host "
                        f"{held.get('host')}, pid {held.get('pid')}, lease until "
                        f"{time.strftime('%H:%M:%S', time.localtime(self._expires(held)))})"
                        "; option lock_timeout sets how long to wait",
                        option="lock_timeout",
                    )
            time.sleep(0.25)
        self._thread = threading.Thread(target=self._renew, name="standgrid-lease", daemon=True)
        self._thread.start()
        return self

    def _renew(self) -> None:
        renewed = time.monotonic()
        while not self._stop.wait(LEASE_SECONDS / 3):
            try:
                self.etag = self.folder.write(LOCK, self._body(), if_match=self.etag)
                renewed = time.monotonic()
            except PreconditionFailed:
                self.lost = True
                return
            except StorageError:  # a network hiccup: the next renewal may get through
                if time.monotonic() - renewed > LEASE_SECONDS * 2 / 3:
                    self.lost = True  # others may take it over soon: commit nothing
                    return

    def release(self) -> None:
        """Give the lease up: its object is rewritten as expired, only while it is still
        this writer's (a conditional write; the next writer takes an expired lease at
        once). Failing to is said, not raised: the lease expires by itself."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self.lost or self.etag is None:
            return
        expired = json.dumps({"owner": self.owner, "released": True, "expires": 0}).encode()
        try:
            self.folder.write(LOCK, expired, if_match=self.etag)
        except StorageError as exc:  # taken over since, or the store is unreachable
            _log.warning("%s: lease not given up (%s); it expires by itself", self.folder.url, exc)


class RemoteCatalog:
    """The catalog at an object-storage URL (see the module doc)."""

    def __init__(self, url: str) -> None:
        self.folder = ObjectFolder.open(url)
        self.url = self.folder.url
        self.name = self.url.rsplit("/", 1)[-1] or "catalog"

    def head(self) -> Head | None:
        """The generation HEAD names now (None: no catalog at this URL)."""
        found = self.folder.read(HEAD)
        if found is None:
            return None
        try:
            body = json.loads(found[0])
            head = Head(int(body["generation"]), str(body["root"]), found[1])
        except (ValueError, KeyError, TypeError) as exc:
            raise StorageError(f"{self.folder.href(HEAD)}: not a standgrid HEAD: {exc}") from exc
        if not _GENERATION.match(head.root) or not head.root.startswith(f"g{head.generation:06d}-"):
            raise StorageError(f"{self.folder.href(HEAD)}: {head.root!r} is no generation")
        return head

    def manifest(self, head: Head) -> dict[str, dict[str, Any]]:
        """Every file of ``head``'s generation: relative path -> size and sha256."""
        key = f"{MANIFESTS}/{head.root}.json"
        found = self.folder.read(key)
        if found is None:
            raise StorageError(f"{self.url}: generation {head.root} has no manifest")
        try:
            files = dict(json.loads(found[0])["files"])
            for rel, entry in files.items():  # a path to write under the working copy
                parts = rel.split("/")
                if rel.startswith("/") or "\\" in rel or any(p in ("", ".", "..") for p in parts):
                    raise ValueError(f"{rel!r} leaves the catalog")
                size, digest = entry["size"], entry["sha256"]
                if type(size) is not int or size < 0 or not isinstance(digest, str):
                    raise ValueError(f"{rel!r}: no size and digest")
        except (ValueError, KeyError, TypeError) as exc:
            raise StorageError(f"{self.folder.href(key)}: not a standgrid manifest: {exc}") from exc
        return files

    def fetch(self, head: Head, files: dict[str, dict[str, Any]], target: Path) -> None:
        """Download generation ``head`` into ``target``, every file checked by its digest."""
        mirror_down(self.folder, {f"{head.root}/{rel}": rel for rel in files}, target)
        for rel, entry in files.items():
            if (target / rel).stat().st_size != entry["size"] or file_sha256(target / rel) != entry[
                "sha256"
            ]:
                raise StorageError(f"{self.folder.href(head.root + '/' + rel)}: damaged copy")

    @contextlib.contextmanager
    def checkout(
        self, *, write: bool, lock_timeout: float | None, only: Sequence[str] = ()
    ) -> Iterator[Path]:
        """A local working copy of the catalog; with ``write``, under the lease, committed
        as a new generation when the block ends without an error (and changed something).
        ``only`` (reading): just these files."""
        if write and only:
            raise ValueError("a working copy to write holds every file")
        if write:
            self._require_conditional_writes()
        lease = Lease(self.folder, lock_timeout).acquire() if write else None
        work = _work_folder("standgrid-catalog-")
        try:
            root = work / self.name
            head, files = self._fetch_current(root, only)
            key = os.path.realpath(root)
            if head is not None:
                _CHECKOUTS[key] = (f"{self.url}/{head.root}", files)
            try:
                yield root
            except StandgridError as exc:  # say the catalog's URL, not the working copy's
                _name_url(exc, work, self.url)
                raise
            finally:
                _CHECKOUTS.pop(key, None)
            if write:
                assert lease is not None
                self._commit(root, head, files, lease)
        finally:
            if write:
                _IN_STORE.clear()  # workers' outputs of this checkout: committed, or not
            if lease is not None:
                lease.release()
            shutil.rmtree(work, ignore_errors=True)

    def _require_conditional_writes(self) -> None:
        """:class:`StorageError` unless the store refuses to create an object twice (a
        store ignoring conditional writes would let two writers both switch HEAD)."""
        probe = f"_standgrid/probe-{uuid.uuid4().hex}"
        self.folder.write(probe, b"", create=True)
        try:
            self.folder.write(probe, b"", create=True)
        except PreconditionFailed:
            return
        finally:
            with contextlib.suppress(StorageError):
                self.folder.delete([probe])
        raise StorageError(
            f"{self.url}: the store ignores conditional writes (If-None-Match): a catalog "
            "there could lose a commit to a concurrent writer; use a store that honours them"
        )

    def _fetch_current(
        self, root: Path, only: Sequence[str]
    ) -> tuple[Head | None, dict[str, dict[str, Any]]]:
        for attempt in range(3):  # a generation deleted while read: read HEAD again
            head = self.head()
            if head is None:
                return None, {}
            try:
                files = self.manifest(head)
                self.fetch(head, {k: files[k] for k in only if k in files} if only else files, root)
                return head, files
            except StorageError:
                shutil.rmtree(root, ignore_errors=True)
                if attempt == 2 or self.head() == head:
                    raise
        raise AssertionError("unreachable")

    def _commit(
        self, root: Path, head: Head | None, old: dict[str, dict[str, Any]], lease: Lease
    ) -> None:
        now = _scan(root)
        if now == old or not now:
            return  # nothing changed (or the stage made no catalog): no new generation
        generation = (head.generation if head else 0) + 1
        new_root = f"g{generation:06d}-{uuid.uuid4().hex[:8]}"
        uploads: dict[str, Path] = {}
        copies: dict[str, str] = {}
        there = self.url + "/"
        for rel, entry in now.items():
            if head is not None and old.get(rel) == entry:
                copies[f"{new_root}/{rel}"] = f"{head.root}/{rel}"
            elif _IN_STORE.get(entry["sha256"], "").startswith(there):
                copies[f"{new_root}/{rel}"] = _IN_STORE[entry["sha256"]][len(there) :]
            else:
                uploads[f"{new_root}/{rel}"] = root / rel
        mirror_up(self.folder, uploads)
        crash_point("remote-uploaded")
        try:
            copy_many(self.folder, copies)
        except StorageError:  # a worker's tile gone from the outbox (collected): upload it
            again = {
                t: root / t.split("/", 1)[1] for t, src in copies.items() if src.startswith(OUTBOX)
            }
            if not again:
                raise
            mirror_up(self.folder, again)
            copy_many(self.folder, {t: src for t, src in copies.items() if t not in again})
        manifest = {"format": FORMAT, "generation": generation, "root": new_root, "files": now}
        self.folder.write(f"{MANIFESTS}/{new_root}.json", _json(manifest), create=True)
        crash_point("remote-before-switch")
        if lease.lost:
            raise CatalogConflictError(f"{self.url}: the writer's lease was lost; not committed")
        body = _json({"format": FORMAT, "generation": generation, "root": new_root})
        try:
            if head is None:
                self.folder.write(HEAD, body, create=True)
            else:
                self.folder.write(HEAD, body, if_match=head.etag)
        except PreconditionFailed as exc:
            raise CatalogConflictError(
                f"{self.url}: another writer committed first; open it again and repeat"
            ) from exc
        crash_point("remote-switched")
        try:  # committed: tidying up can fail (a policy without DeleteObject), and is said
            self._collect({new_root} | ({head.root} if head else set()))
        except StorageError as exc:
            _log.warning("%s: committed; old generations not removed (%s)", self.url, exc)

    def _collect(self, keep: set[str]) -> None:
        """Delete generations (and manifests) other than ``keep``: older ones and the
        remains of killed commits (the lease is held: no other writer is uploading)."""
        stale = []
        for meta in self.folder.list():
            key = meta["path"]
            top = key.split("/", 1)[0]
            generation = bool(_GENERATION.match(top)) and "/" in key and top not in keep
            outbox = key.startswith(OUTBOX + "/")  # workers' tiles, copied in by now
            if (
                generation
                or outbox
                or (key.startswith(MANIFESTS + "/") and Path(key).stem not in keep)
            ):
                stale.append(key)
        self.folder.delete(stale)


def current_state(url: str) -> dict[str, Any] | None:
    """The ``catalog.json`` of the generation current at ``url`` (None: no catalog)."""
    remote = RemoteCatalog(url)
    head = remote.head()
    found = remote.folder.read(f"{head.root}/{CATALOG_FILE}") if head else None
    return None if found is None else dict(json.loads(found[0]))


def outbox_url(url: str) -> str:
    """A new folder under the catalog at ``url`` for workers to put their outputs in (removed
    by the commit that takes them, or the next one)."""
    return f"{url.rstrip('/')}/{OUTBOX}/{uuid.uuid4().hex[:12]}"


def _name_url(exc: StandgridError, work: Path, url: str) -> None:
    """An error's text with the working copy's paths said as the catalog's URL."""
    folders = {str(work), os.path.realpath(work)}
    for folder in sorted(folders, key=len, reverse=True):
        text = str(exc.args[0]) if exc.args else exc.message
        named = text.replace(f"{folder}/{url.rsplit('/', 1)[-1]}", url).replace(folder, url)
        exc.args = (named, *exc.args[1:])
        exc.message = exc.message.replace(folder, url)


def _json(body: dict[str, Any]) -> bytes:
    return json.dumps(body, indent=1, sort_keys=True).encode()


def _scan(root: Path) -> dict[str, dict[str, Any]]:
    """Every file of the catalog folder ``root`` (staging left out): size and sha256."""
    if not (root / CATALOG_FILE).is_file():
        return {}
    files = {}
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root).as_posix()
        if path.is_file() and not rel.startswith(STAGING_DIR + "/"):
            files[rel] = {"size": path.stat().st_size, "sha256": file_sha256(path)}
    return files


@contextlib.contextmanager
def catalog_at(
    location: str | Path,
    *,
    write: bool,
    lock_timeout: float | None = None,
    only: Sequence[str] = (),
) -> Iterator[Path]:
    """The catalog at ``location`` as a local folder: a path is itself; an object-storage
    URL is checked out (and, with ``write``, committed back: see the module doc; reading,
    ``only`` these files when given). Reading a URL that holds no catalog is
    :class:`CatalogNotFoundError`."""
    if not is_url(location):
        yield Path(location)
        return
    remote = RemoteCatalog(str(location))
    if not write and remote.head() is None:
        raise CatalogNotFoundError(f"{remote.url}: no standgrid catalog here")
    with remote.checkout(write=write, lock_timeout=lock_timeout, only=only) as root:
        yield root
