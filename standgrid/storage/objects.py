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


class PreconditionFailed(StorageError):
    """A conditional write found the object not as expected (created or changed by another
    writer since it was read)."""


def is_url(location: object) -> bool:
    """Whether ``location`` names object storage (``s3://…``) rather than a local path."""
    return isinstance(location, str) and bool(_URL.match(location))


@contextlib.contextmanager
def _reported(url: str, what: str) -> Iterator[None]:
    """obstore's errors as :class:`StorageError` naming the URL."""
    from obstore import exceptions as ox

    try:
        yield
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
            with contextlib.suppress(ImportError):
                from obstore.auth.boto3 import Boto3CredentialProvider

                options["credential_provider"] = Boto3CredentialProvider()
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
        self, key: str, data: bytes, *, create: bool = False, if_match: str | None = None
    ) -> str | None:
        """Write ``data`` at ``key``; ``create``: only if absent; ``if_match``: only if its
        ETag is still that (:class:`PreconditionFailed` otherwise). Returns the new ETag."""
        import obstore

        mode: Any = "create" if create else ({"e_tag": if_match} if if_match else "overwrite")
        with _reported(self.href(key), "write"):
            return obstore.put(self.store, key, data, mode=mode, use_multipart=False)["e_tag"]

    def upload(self, path: Path, key: str) -> None:
        """Put the file ``path`` at ``key`` (multipart above :data:`PART_BYTES`)."""
        import obstore

        with _reported(self.href(key), f"upload {path}"):
            obstore.put(self.store, key, Path(path), chunk_size=PART_BYTES, max_concurrency=4)

    def download(self, key: str, path: Path) -> int:
        """Stream ``key`` into the file ``path`` (made with its folders); returns its size."""
        import obstore

        path.parent.mkdir(parents=True, exist_ok=True)
        size = 0
        with _reported(self.href(key), "download"), open(path, "wb") as out:
            for chunk in obstore.get(self.store, key).stream(min_chunk_size=PART_BYTES):
                out.write(chunk)
                size += len(chunk)
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


def fetched_folder(url: str, cache: Path | None = None) -> Path:
    """The objects under ``url`` as a local folder ``cache/<digest>/<last segment>``, or the
    one object ``url`` names as that file; kept between runs and refreshed by size (a
    mission keeps its folder, and so its identity)."""
    import hashlib

    url = url.rstrip("/")
    digest = hashlib.sha256(url.encode()).hexdigest()[:16]
    target = (cache or local_cache()) / digest / url.rsplit("/", 1)[-1]
    folder = ObjectFolder.open(url)
    wanted = {m["path"]: m["size"] for m in folder.list()}
    if not wanted:  # one object (a plain scan: LAS/LAZ/COPC, a VPC): into the same folder
        parent, _, name = url.rpartition("/")
        folder = ObjectFolder.open(parent)
        size = folder.size(name) if is_url(parent) else None
        if size is None:
            raise StorageError(f"{url}: no objects here")
        target = target.parent
        wanted = {name: size}
    stale = {
        key: key
        for key, size in wanted.items()
        if not (target / key).is_file() or (target / key).stat().st_size != size
    }
    mirror_down(folder, stale, target)
    return target
