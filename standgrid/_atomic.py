"""Write-then-rename helpers: no reader ever sees a half-written output."""

from __future__ import annotations

import contextlib
import os
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path

from standgrid.errors import OutputExistsError, OutputNotWritableError


def temporary_sibling(final: Path) -> Path:
    """A unique hidden name in the same folder as ``final`` (so the rename is atomic)."""
    return final.with_name(f".{final.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp")


def _swap_folder(new: Path, final: Path) -> None:
    """Replace the folder ``final`` by ``new``: move the old one aside, move the new one in,
    then delete the old one. If the new one cannot be moved in, the old one is put back and
    :class:`OutputNotWritableError` is raised (``final`` is left as it was)."""
    old = temporary_sibling(final)
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


@contextlib.contextmanager
def atomic_output(final: str | os.PathLike[str], *, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``final``; on success rename it onto ``final``.

    Works for a file or a folder written at the temporary path. On error the temporary is
    removed and ``final`` is left as it was.
    """
    final_path = Path(final)
    if final_path.exists() and not overwrite:
        raise OutputExistsError("exists (use overwrite to replace it)", path=final_path)
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
        if tmp.is_dir() and final_path.is_dir():
            _swap_folder(tmp, final_path)
        else:
            os.replace(tmp, final_path)
    except BaseException:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            tmp.unlink(missing_ok=True)
        raise


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Write a text file atomically (UTF-8, ``\\n`` line ends)."""
    with atomic_output(path) as tmp:
        tmp.write_text(text, encoding="utf-8", newline="\n")
