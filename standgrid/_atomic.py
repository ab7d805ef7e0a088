"""Write-then-rename helpers: no reader ever sees a half-written output.

Durability follows SQLite's rules: a file's data is ``fsync``-ed before it is renamed into
place, and the folder holding the new name is ``fsync``-ed after the rename, so a power
loss leaves the old or the new file, never a torn one.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import shutil
import stat
import uuid
from collections.abc import Callable, Collection, Iterator
from pathlib import Path

from standgrid.errors import (
    OVERWRITE_HINT,
    OutputExistsError,
    OutputNotWritableError,
    StandgridError,
    out_of_space_error,
)


def temporary_sibling(final: Path, kind: str = "") -> Path:
    """A unique hidden name in the same folder as ``final`` (so the rename is atomic).

    ``.<name>.<kind->pid-id.tmp``: the pid tells a live builder from a dead one.
    """
    tag = f"{kind}-" if kind else ""
    return final.with_name(f".{final.name}.{tag}{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp")


def fsync_path(path: str | os.PathLike[str]) -> None:
    """``fsync`` a file or a folder (its data, or its entries) by path."""
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if Path(path).is_dir() else 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def start_writeback(path: Path) -> None:
    """Start writing a file's data to disk without waiting (a later fsync then mostly
    finds it done); its pages leave the cache once written."""
    fd = os.open(path, os.O_RDONLY)
    try:
        if hasattr(os, "posix_fadvise"):
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)


#: What identifies a file's content on disk: device, inode, size, mtime and ctime (ns).
FileIdentity = tuple[int, int, int, int, int]


def file_identity(path: str | os.PathLike[str]) -> FileIdentity | None:
    """The :data:`FileIdentity` of a regular file (None: absent, or not a regular file).
    Any write, rename or metadata change of the file changes its ctime."""
    try:
        st = os.stat(path, follow_symlinks=False)
    except OSError:
        return None
    if not stat.S_ISREG(st.st_mode):
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def fsync_tree(root: Path, *, durable: Collection[FileIdentity] = ()) -> None:
    """``fsync`` every file and folder under ``root`` (a freshly written output).

    ``durable``: identities (:func:`file_identity`) of files whose data is known to be on
    the disk already (fsynced, unchanged since); they are not fsynced again, their folders
    still are."""
    if root.is_dir() and not root.is_symlink():
        for folder, _dirs, files in os.walk(root):
            for name in files:
                full = Path(folder) / name
                if full.is_symlink() or (durable and file_identity(full) in durable):
                    continue
                fsync_path(full)
            fsync_path(folder)
    elif root.exists():
        fsync_path(root)


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def exchange(a: Path, b: Path) -> bool:
    """Swap two paths atomically (Linux ``renameat2(RENAME_EXCHANGE)``).

    Returns False where the system cannot (then nothing was changed).
    """
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [
        ctypes.c_int,
        ctypes.c_char_p,
        ctypes.c_int,
        ctypes.c_char_p,
        ctypes.c_uint,
    ]
    result = renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    if result == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(code, os.strerror(code), os.fspath(a), None, os.fspath(b))


def _swap_folder(new: Path, final: Path) -> None:
    """Replace the folder ``final`` by ``new``, so that ``final`` always exists.

    An atomic exchange where the system has one; otherwise the old folder is moved aside
    (``.<name>.old-<pid>-<id>.tmp``, put back if the new one cannot be moved in). The old
    folder is deleted last. Raises :class:`OutputNotWritableError` (``final`` left as it was).
    """
    try:
        if exchange(new, final):
            shutil.rmtree(new, ignore_errors=True)
            return
    except OSError as exc:
        raise OutputNotWritableError(
            f"cannot move the new output into place: {exc.strerror}", path=final
        ) from exc
    old = temporary_sibling(final, "old")
    try:
        os.replace(final, old)
    except OSError as exc:
        raise OutputNotWritableError(
            f"cannot move the old output aside: {exc.strerror}", path=final
        ) from exc
    try:
        os.replace(new, final)
    except OSError as exc:
        os.replace(old, final)
        raise OutputNotWritableError(
            f"cannot move the new output into place: {exc.strerror}", path=final
        ) from exc
    shutil.rmtree(old, ignore_errors=True)


def _place_new(tmp: Path, final: Path) -> None:
    """Put ``tmp`` at ``final`` only if nothing is there, in one step (another writer that
    created ``final`` after the first check is never overwritten)."""
    import errno

    try:
        if tmp.is_dir():
            os.rename(tmp, final)  # fails onto a file or a non-empty folder
        else:
            os.link(tmp, final)  # fails when final exists
            tmp.unlink()
    except OSError as exc:
        if exc.errno in (errno.EEXIST, errno.ENOTEMPTY, errno.ENOTDIR, errno.EISDIR):
            raise OutputExistsError(
                f"exists (written by another process meanwhile; {OVERWRITE_HINT})",
                path=final,
            ) from exc
        raise


def check_replaceable(
    final: Path,
    *,
    overwrite: bool,
    replaces: Callable[[Path], bool] | None = None,
    what: str = "an output of this kind",
) -> None:
    """Refuse to replace ``final`` unless ``overwrite``, and a folder with files even then
    unless it is ``what`` (``replaces(final)``): overwriting never deletes a folder of other
    things (a folder of missions, a home folder) given as an output by mistake."""
    if not final.exists() and not final.is_symlink():
        return
    if final.is_symlink() and overwrite:
        raise OutputExistsError(
            "is a symbolic link: overwriting would replace the link, not what it points to "
            "(give the folder it points to, or another output)",
            path=final,
        )
    if not overwrite:
        raise OutputExistsError(f"exists ({OVERWRITE_HINT})", path=final)
    if (
        final.is_dir()
        and not final.is_symlink()
        and any(final.iterdir())
        and not (replaces is not None and replaces(final))
    ):
        raise OutputExistsError(
            f"is a folder with files that is not {what}: overwriting replaces only {what} "
            "(choose another output, or move the folder away yourself)",
            path=final,
        )


@contextlib.contextmanager
def atomic_output(
    final: str | os.PathLike[str],
    *,
    overwrite: bool = True,
    durable: bool = True,
    replaces: Callable[[Path], bool] | None = None,
    what: str = "an output of this kind",
) -> Iterator[Path]:
    """Yield a temporary path beside ``final``; on success rename it onto ``final``.

    Works for a file or a folder written at the temporary path; the data is fsynced before
    the rename and the folder after it. ``durable=False`` (a file staged in a catalog
    transaction, whose commit fsyncs every staged file): the write-back of a file is only
    started, not waited for. On error the temporary is removed and ``final`` is left as it
    was; running out of space raises :class:`~standgrid.errors.OutOfSpaceError`. An
    existing folder with files is replaced only when ``replaces(final)`` says it is ``what``
    (:func:`check_replaceable`).
    """
    final_path = Path(final)
    check_replaceable(final_path, overwrite=overwrite, replaces=replaces, what=what)
    try:
        final_path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputNotWritableError(
            f"cannot create folder: {exc.strerror}", path=final_path.parent
        ) from exc
    if not os.access(final_path.parent, os.W_OK):
        raise OutputNotWritableError("folder is not writable", path=final_path.parent)
    tmp = temporary_sibling(final_path)
    try:
        yield tmp
        if durable:
            fsync_tree(tmp)
        elif tmp.is_file():
            start_writeback(tmp)
        if not overwrite:
            _place_new(tmp, final_path)
        elif tmp.is_dir() and final_path.is_dir():
            _swap_folder(tmp, final_path)
        elif final_path.is_dir():  # a file never replaces a folder, even an empty one
            raise OutputExistsError("is a folder (the output is a file)", path=final_path)
        else:
            os.replace(tmp, final_path)
        if durable:
            fsync_path(final_path.parent)
    except BaseException as exc:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            tmp.unlink(missing_ok=True)
        full = None if isinstance(exc, StandgridError) else out_of_space_error(exc, final_path)
        if full is not None:
            raise full from exc
        raise


def write_text_atomic(path: str | os.PathLike[str], text: str, *, durable: bool = True) -> None:
    """Write a text file atomically and durably (UTF-8, ``\\n`` line ends); ``durable=False``
    for a file staged in a catalog transaction (its commit fsyncs it, see
    :func:`atomic_output`)."""
    with atomic_output(path, durable=durable) as tmp:
        tmp.write_text(text, encoding="utf-8", newline="\n")
