"""A folder of objects in object storage, opened from its URL (obstore underneath).

``s3://bucket/prefix`` (and ``gs://``, ``az://``, ``abfs://``, ``http(s)://`` read-only) is
an :class:`ObjectFolder`: keys are relative to its prefix. Credentials come from where the
store's own clients look: ``AWS_ACCESS_KEY_ID``/``AWS_SECRET_ACCESS_KEY``/
``AWS_SESSION_TOKEN``, ``AWS_REGION``, ``AWS_ENDPOINT_URL`` (an S3-compatible server; an
``http://`` endpoint is allowed), and, with boto3 installed, ``AWS_PROFILE`` and the
instance/role chain; Google and Azure read their usual variables. Nothing about credentials
is ever written to a catalog.

Large files go up as multipart uploads and come down in streamed chunks; reads of a part
are ranged reads.
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from standgrid.errors import StorageError

#: What :func:`is_url` takes for object storage (``file://`` stays a path).
_URL = re.compile(r"^(s3|s3a|gs|gcs|az|azure|abfs|abfss|http|https)://[^/]", re.IGNORECASE)
#: Transfers at once when mirroring a folder (network-bound threads, not cores).
TRANSFER_THREADS = 8
#: Part size of multipart uploads and of streamed downloads.
PART_BYTES = 8 * 1024 * 1024


#: :meth:`ObjectFolder.write` without a condition (the default; a ``None`` ETag is none).
UNCONDITIONAL = object()


class PreconditionFailed(StorageError):
    """A conditional write found the object not as expected (created or changed by another
    writer since it was read)."""


def file_sha256(path: str | os.PathLike[str]) -> str:
    """The SHA-256 of a file, read in 1 MiB blocks."""
    import hashlib

    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            digest.update(block)
    return digest.hexdigest()


def is_url(location: object) -> bool:
    """Whether ``location`` names object storage (``s3://…``) rather than a local path."""
    return isinstance(location, str) and bool(_URL.match(location))


@contextlib.contextmanager
def _reported(url: str, what: str) -> Iterator[None]:
    """obstore's errors as :class:`StorageError` naming the URL."""
    from obstore import exceptions as ox

    try:
        yield
    except StorageError:  # said already, with its URL
        raise
    except (ox.AlreadyExistsError, ox.PreconditionError) as exc:
        raise PreconditionFailed(f"{url}: {what}: changed by another writer") from exc
    except (ox.NotFoundError, FileNotFoundError) as exc:
        raise StorageError(f"{url}: {what}: no such object") from exc
    except (ox.BaseError, OSError) as exc:  # permissions, network, configuration
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise StorageError(f"{url}: {what}: {first}") from exc


def _open_store(url: str) -> Any:
    from obstore.store import from_url

    options: dict[str, Any] = {}
    scheme = url.split("://", 1)[0].lower()
    if scheme in ("s3", "s3a"):
        endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
        if endpoint:
            options["endpoint"] = endpoint
        client = {"allow_http": True} if (endpoint or "").startswith("http://") else {}
        if not os.environ.get("AWS_ACCESS_KEY_ID") and os.environ.get("AWS_PROFILE"):
            try:
                from botocore.exceptions import BotoCoreError
                from obstore.auth.boto3 import Boto3CredentialProvider
            except ImportError as exc:
                raise StorageError(
                    f"{url}: AWS_PROFILE is set: reading profiles needs boto3 "
                    "(pip install boto3), or set AWS_ACCESS_KEY_ID/AWS_SECRET_ACCESS_KEY"
                ) from exc
            try:
                options["credential_provider"] = Boto3CredentialProvider()
            except BotoCoreError as exc:  # no such profile, a broken config file
                raise StorageError(f"{url}: AWS_PROFILE: {exc}") from exc
        opener: Any = from_url  # its overloads type each store's options apart
        return opener(url.replace("s3a://", "s3://", 1), client_options=client, **options)
    return from_url(url)


@dataclass(frozen=True)
class ObjectFolder:
    """The objects under one URL prefix; keys are relative (``tiles/1/c.laz``)."""

    url: str
    store: Any

    @classmethod
    def open(cls, url: str) -> ObjectFolder:
        """The folder at ``url`` (no request is made yet)."""
        url = url.rstrip("/")
        if not is_url(url):
            raise StorageError(f"{url}: not an object-storage URL (s3://bucket/prefix, …)")
        from urllib.parse import urlsplit

        parts = urlsplit(url)
        if parts.username or parts.password or parts.query or parts.fragment:
            shown = f"{parts.scheme}://{parts.hostname or ''}{parts.path}"
            raise StorageError(
                f"{shown}: credentials or parameters in the URL are not taken (they would be "
                "written to catalogs and messages): give them in the environment"
            )
        if any(p in (".", "..") for p in parts.path.split("/")):
            raise StorageError(f"{url}: '.' and '..' are no folder names in object storage")
        with _reported(url, "open"):
            return cls(url, _open_store(url))

    def __getstate__(self) -> str:  # sent to dask workers as its URL, reopened there
        return self.url

    def __setstate__(self, url: str) -> None:
        object.__setattr__(self, "url", url)
        object.__setattr__(self, "store", _open_store(url))

    def href(self, key: str) -> str:
        """The URL of ``key``."""
        return f"{self.url}/{key}"

    def read(self, key: str) -> tuple[bytes, str | None] | None:
        """The object's bytes and ETag; None when there is no such object."""
        import obstore
        from obstore import exceptions as ox

        with _reported(self.href(key), "read"):
            try:
                result = obstore.get(self.store, key)
            except (ox.NotFoundError, FileNotFoundError):  # obstore raises the latter
                return None
            return bytes(result.bytes()), result.meta.get("e_tag")

    def read_range(self, key: str, start: int, end: int) -> bytes:
        """Bytes ``start`` to ``end`` (exclusive) of ``key``: one ranged read."""
        import obstore

        with _reported(self.href(key), f"read bytes {start}-{end}"):
            return bytes(obstore.get_range(self.store, key, start=start, end=end))

    def write(
        self, key: str, data: bytes, *, create: bool = False, if_match: object = UNCONDITIONAL
    ) -> str | None:
        """Write ``data`` at ``key``; ``create``: only if absent; ``if_match``: only if its
        ETag is still that (:class:`PreconditionFailed` otherwise; an ETag of None, from a
        store that gives none, is a :class:`StorageError`, never an overwrite). Returns the
        new ETag."""
        import obstore

        if create:
            mode: Any = "create"
        elif if_match is UNCONDITIONAL:
            mode = "overwrite"
        elif isinstance(if_match, str) and if_match:
            mode = {"e_tag": if_match}
        else:
            raise StorageError(
                f"{self.href(key)}: the store gave no ETag: it cannot be written conditionally"
            )
        with _reported(self.href(key), "write"):
            return obstore.put(self.store, key, data, mode=mode, use_multipart=False)["e_tag"]

    def upload(self, path: Path, key: str) -> None:
        """Put the file ``path`` at ``key`` (multipart above :data:`PART_BYTES`)."""
        import obstore

        with _reported(self.href(key), f"upload {path}"):
            obstore.put(self.store, key, Path(path), chunk_size=PART_BYTES, max_concurrency=4)

    def download(self, key: str, path: Path) -> int:
        """Stream ``key`` into the file ``path`` (made with its folders); returns its size."""
        import threading

        import obstore

        size = 0
        part = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.part")
        with _reported(self.href(key), "download"):
            path.parent.mkdir(parents=True, exist_ok=True)
            try:
                with open(part, "wb") as out:
                    for chunk in obstore.get(self.store, key).stream(min_chunk_size=PART_BYTES):
                        out.write(chunk)
                        size += len(chunk)
                os.replace(part, path)  # whole, or not there: never a torn file
            finally:
                with contextlib.suppress(FileNotFoundError):
                    part.unlink()
        return size

    def copy(self, source: str, target: str) -> None:
        """Copy ``source`` to ``target`` inside the store (no bytes through this process)."""
        import obstore

        with _reported(self.href(source), f"copy to {target}"):
            obstore.copy(self.store, source, target)

    def size(self, key: str) -> int | None:
        """The object's size; None when there is no such object."""
        import obstore
        from obstore import exceptions as ox

        with _reported(self.href(key), "head"):
            try:
                return int(obstore.head(self.store, key)["size"])
            except (ox.NotFoundError, FileNotFoundError):
                return None

    def list(self, prefix: str = "") -> list[dict[str, Any]]:
        """Every object under ``prefix`` (``path`` relative to the folder, ``size``,
        ``e_tag``)."""
        import obstore

        with _reported(self.href(prefix), "list"):
            return [dict(m) for batch in obstore.list(self.store, prefix or None) for m in batch]

    def delete(self, keys: Iterable[str]) -> None:
        """Delete ``keys`` (absent ones are no error)."""
        import obstore

        keys = list(keys)
        for start in range(0, len(keys), 1000):
            with _reported(self.url, f"delete {len(keys)} objects"):
                obstore.delete(self.store, keys[start : start + 1000])


def mirror_down(folder: ObjectFolder, keys: dict[str, str], root: Path) -> int:
    """Download ``keys`` (object key -> path relative to ``root``) into ``root``, several at
    once; returns the bytes read."""
    with ThreadPoolExecutor(TRANSFER_THREADS, thread_name_prefix="standgrid-get") as pool:
        return sum(pool.map(lambda kv: folder.download(kv[0], root / kv[1]), keys.items()))


def mirror_up(folder: ObjectFolder, files: dict[str, Path]) -> None:
    """Upload ``files`` (object key -> local file), several at once."""
    with ThreadPoolExecutor(TRANSFER_THREADS, thread_name_prefix="standgrid-put") as pool:
        for _ in pool.map(lambda kv: folder.upload(kv[1], kv[0]), files.items()):
            pass


def copy_many(folder: ObjectFolder, pairs: dict[str, str]) -> None:
    """Server-side copies (target key -> source key), several at once."""
    with ThreadPoolExecutor(TRANSFER_THREADS, thread_name_prefix="standgrid-copy") as pool:
        for _ in pool.map(lambda kv: folder.copy(kv[1], kv[0]), pairs.items()):
            pass


def local_cache() -> Path:
    """Where fetched folders are kept: ``$STANDGRID_WORK_DIR`` or the temporary folder."""
    import tempfile

    return Path(os.environ.get("STANDGRID_WORK_DIR") or tempfile.gettempdir()) / "standgrid-cache"


#: Local folders fetched from object storage (real path -> the URL they hold).
_FETCHED: dict[str, str] = {}


def source_of(path: str | os.PathLike[str]) -> str:
    """Where ``path`` came from: the URL of a folder (or file) fetched by
    :func:`fetched_folder` in this process, or of something inside one; else its real
    path."""
    real = os.path.realpath(path)
    for folder, url in _FETCHED.items():  # the folder itself, or inside it (a folder of missions)
        if real == folder or real.startswith(folder + os.sep):
            return url + real[len(folder) :].replace(os.sep, "/")
    return real


def local_copy(location: str | os.PathLike[str]) -> Path:
    """``location`` as a local path: an object-storage URL fetched (:func:`fetched_folder`),
    a path as it is."""
    return fetched_folder(str(location)) if is_url(location) else Path(location)


def check_key(key: str, where: str) -> str:
    """``key`` when it stays inside its folder (no ``..``, ``.``, empty or absolute parts),
    else :class:`StorageError` naming ``where``."""
    parts = key.split("/")
    if not key or key.startswith("/") or "\\" in key or any(p in ("", ".", "..") for p in parts):
        raise StorageError(f"{where}: {key!r} leaves its folder")
    return key


def fetched_folder(url: str, cache: Path | None = None) -> Path:
    """The objects under ``url`` as a local folder ``cache/<digest>/<last segment>``, or the
    one object ``url`` names as that file. Kept between runs and refreshed by size and
    ETag; files whose objects are gone are removed (a mission keeps its folder, so its
    identity: :func:`source_of` gives its URL back)."""
    import hashlib
    import json

    url = url.rstrip("/")
    digest = hashlib.sha256(url.encode()).hexdigest()[:16]
    target = (cache or local_cache()) / digest / url.rsplit("/", 1)[-1]
    folder = ObjectFolder.open(url)
    wanted = {check_key(m["path"], url): (m["size"], m.get("e_tag")) for m in folder.list()}
    single = not wanted
    if single:  # one object (a plain scan: LAS/LAZ/COPC, a VPC): into the same folder
        parent, _, name = url.rpartition("/")
        folder = ObjectFolder.open(parent)
        size = folder.size(name) if is_url(parent) else None
        if size is None:
            raise StorageError(f"{url}: no objects here")
        target = target.parent
        wanted = {name: (size, None)}
    state_file = (target if single else target.parent) / ".objects.json"  # size and ETag
    try:
        held = {k: tuple(v) for k, v in json.loads(state_file.read_text()).items()}
    except (OSError, ValueError, AttributeError):
        held = {}
    stale = {
        key: key
        for key, (size, etag) in wanted.items()
        if not (target / key).is_file()
        or (target / key).stat().st_size != size
        or (etag is not None and held.get(key) != (size, etag))
    }
    mirror_down(folder, stale, target)
    if not single:  # files whose objects are gone
        for path in sorted(target.rglob("*"), reverse=True):
            rel = path.relative_to(target).as_posix()
            if path.is_file() and rel not in wanted:
                path.unlink()
    state_file.parent.mkdir(parents=True, exist_ok=True)
    state_file.write_text(json.dumps({k: list(v) for k, v in wanted.items()}))
    fetched = target if not single else target / next(iter(wanted))
    _FETCHED[os.path.realpath(fetched)] = url
    return fetched
