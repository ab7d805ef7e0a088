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
            old = temporary_sibling(final_path)
            os.replace(final_path, old)
            os.replace(tmp, final_path)
            shutil.rmtree(old, ignore_errors=True)
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
