"""The catalog's locks: ``flock`` on two files *beside* the catalog folder, so they also cover
creating and replacing it.

``.<name>.lock`` is the writer lock, held by a writer from before it reads the catalog until
after it commits, so two writers never both succeed with one's work lost (the second waits up
to ``lock_timeout`` seconds, then :class:`CatalogBusyError`). ``.<name>.readers.lock`` is
taken exclusively only while a commit moves files into place, and shared by readers
(``Catalog.reading``, briefly by ``Catalog.open``), so a reader holding it sees the old or the
new catalog, never a mix. A writer waits for readers up to ``lock_timeout`` too (then
:class:`CatalogBusyError` naming who holds the lock); every wait longer than a second is
logged (``standgrid.catalog``, INFO; the CLI prints it).
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Iterator
from pathlib import Path

from standgrid.engine.execution import DEFAULT_LOCK_TIMEOUT  # what a writer waits: 30 s
from standgrid.errors import CatalogBusyError, OutputNotWritableError


def absolute_root(path: str | os.PathLike[str]) -> Path:
    """The catalog path made absolute with symlinks resolved ("." and "x/" included)."""
    resolved = Path(os.path.realpath(os.fspath(path)))
    if not resolved.name:
        raise OutputNotWritableError("a catalog cannot be the file-system root", path=path)
    return resolved


def lock_paths(path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """The writer and the readers lock files of the catalog at ``path`` (beside it)."""
    root = absolute_root(path)
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
        {
            int(f[4])
            for f in (line.split() for line in lines)
            if len(f) > 5 and f[1] == "FLOCK" and f[5] == key and f[4].isdigit()
        }
    )
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
            raise OutputNotWritableError(
                f"cannot open the lock file: {exc.strerror}", path=self.path
            ) from exc
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
                        "%s: waiting for %s%s%s",
                        _catalog_of(self.path),
                        "readers to finish" if what == "reading" else f"another process {what} it",
                        f" ({'; '.join(holders)})" if holders else "",
                        limit,
                    )
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
def readers_excluded(
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
