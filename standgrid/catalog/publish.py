"""A catalog built beside its final place, and put there atomically for readers."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
from collections.abc import Iterable
from pathlib import Path

from standgrid._atomic import (
    FileIdentity,
    exchange,
    file_identity,
    fsync_path,
    fsync_tree,
    temporary_sibling,
)
from standgrid.catalog.journal import crash_point, pid_alive
from standgrid.catalog.lock import DEFAULT_LOCK_TIMEOUT, absolute_root, readers_excluded
from standgrid.catalog.paths import CATALOG_FILE

#: Catalog folder (real path) -> identities of the files the last commit in this process
#: made durable there (:meth:`Transaction.apply`); :func:`publish` fsyncs only the others.
_COMMITTED: dict[str, set[FileIdentity]] = {}
_COMMITTED_ROOTS = 8


def note_committed(root: Path, files: Iterable[Path]) -> None:
    """The files a commit at ``root`` put in place and made durable (data fsynced before the
    journal, folders after the renames): publishing a catalog built there need not fsync
    them again."""
    placed = (file_identity(path) for path in files)
    _COMMITTED[os.path.realpath(root)] = {ident for ident in placed if ident is not None}
    while len(_COMMITTED) > _COMMITTED_ROOTS:  # a long-lived process: the latest only
        del _COMMITTED[next(iter(_COMMITTED))]


def build_folder(final: Path) -> Path:
    """A fresh hidden sibling to build a catalog in (``.<name>.build-<pid>-<id>.tmp``)."""
    return temporary_sibling(absolute_root(final).parent / Path(final).name, "build")


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
    with readers_excluded(final, timeout):
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
        if match and sibling.is_dir() and not sibling.is_symlink() and not pid_alive(int(match[2])):
            siblings.append((match[1] or "", sibling))
    complete = (path / CATALOG_FILE).is_file()
    if not complete:
        olds = sorted(
            (s for kind, s in siblings if kind == "old" and (s / CATALOG_FILE).is_file()),
            key=lambda s: s.stat().st_mtime,
        )
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
