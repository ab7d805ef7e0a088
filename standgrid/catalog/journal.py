"""The commit journal and crash recovery.

A transaction's journal ``.staging/<txn>/journal.json`` (targets, deletions, generation,
sha256 of its body) is written and fsynced once every staged file is on the disk; then the
staged files are renamed into place, ``catalog.json`` last, the folders fsynced, deletions
done and the staging folder removed (:func:`apply_journal`). A commit killed after the
journal is completed by the next writer or reader (:func:`roll_forward`); one killed before
it, or a torn journal (bad checksum), is discarded, leaving the previous state. Journal
targets must be plain relative paths inside the catalog whose folders are not symlinks;
sources are derived from the targets, never read from the journal.

:func:`crash_point` names the commit points where the crash harness
(``benchmarks/crash_catalog.py``, ``$STANDGRID_CRASH_AT``) kills the process.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from standgrid._atomic import fsync_path, write_text_atomic
from standgrid.catalog.lock import DEFAULT_LOCK_TIMEOUT, readers_excluded, writer_lock
from standgrid.catalog.paths import CATALOG_FILE
from standgrid.catalog.state import STAGING_DIR, read_state, refuse_symlinks, relative_path
from standgrid.errors import CatalogBusyError, CatalogError

JOURNAL_FILE = "journal.json"
#: Environment variable naming a commit point at which the process kills itself (crash tests).
CRASH_ENV = "STANDGRID_CRASH_AT"


def crash_point(name: str) -> None:
    """Die by SIGKILL here when ``$STANDGRID_CRASH_AT`` names this point (crash harness)."""
    wanted = os.environ.get(CRASH_ENV)
    if wanted and wanted == name:
        import signal

        os.kill(os.getpid(), signal.SIGKILL)


def _digest(body: Mapping[str, Any]) -> str:
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode("utf-8")).hexdigest()


def write_journal(folder: Path, body: Mapping[str, Any]) -> Path:
    """Write a transaction's journal into its staging ``folder``, durably: its data, then its
    folder (the one fsync that makes it count)."""
    path = folder / JOURNAL_FILE
    write_text_atomic(path, json.dumps({"journal": body, "sha256": _digest(body)}) + "\n")
    return path


def read_journal(journal_path: Path) -> dict[str, Any] | None:
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
            rel = relative_path(item)
        except CatalogError as exc:
            raise CatalogError(
                f"journal path escapes the catalog: {item!r}", path=journal_path
            ) from exc
        refuse_symlinks(root, rel)
        checked.append(rel)
    return checked[: len(renames)], checked[len(renames) :]


def apply_journal(root: Path, journal_path: Path) -> None:
    """Rename staged files into place (catalog.json last), fsync, delete, drop the staging.

    Sources are ``<journal folder>/files/<target>``, never taken from the journal.
    Idempotent: a rename already done (staged file gone, target present) is skipped. A torn
    journal raises :class:`CatalogError` (recovery discards it instead).
    """
    body = read_journal(journal_path)
    if body is None:
        raise CatalogError("torn or tampered journal (checksum mismatch)", path=journal_path)
    renames, deletes = _journal_targets(root, body, journal_path)
    if _is_superseded(root, body):  # replaying its deletes would hit newer files
        shutil.rmtree(journal_path.parent, ignore_errors=True)
        fsync_path(journal_path.parent.parent)
        return
    files = journal_path.parent / "files"
    if (files / CATALOG_FILE).exists():
        read_state(files / CATALOG_FILE)  # a journal never installs a broken catalog.json
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
    drop_empty_staging(root)


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


def drop_empty_staging(root: Path) -> None:
    with contextlib.suppress(OSError):  # not empty (another transaction) or already gone
        (root / STAGING_DIR).rmdir()


def staging_folders(root: Path) -> Iterator[Path]:
    staging = root / STAGING_DIR
    if staging.is_dir() and not staging.is_symlink():
        yield from sorted(p for p in staging.iterdir() if p.is_dir() and not p.is_symlink())


def journals(root: Path) -> list[Path]:
    return [f / JOURNAL_FILE for f in staging_folders(root) if (f / JOURNAL_FILE).is_file()]


def roll_forward(root: Path) -> list[str]:
    """Complete every journaled (dead) commit; torn journals are discarded. Needs the readers
    lock exclusively."""
    done = []
    for journal in journals(root):
        if read_journal(journal) is None:
            shutil.rmtree(journal.parent, ignore_errors=True)
            done.append(f"discarded {journal.parent.name} (torn journal)")
            continue
        apply_journal(root, journal)
        done.append(f"completed {journal.parent.name}")
    drop_empty_staging(root)
    return done


def recover(root: str | os.PathLike[str]) -> list[str]:
    """Complete journaled transactions, discard unjournaled ones; returns what was done.

    Does nothing while another process holds the writer lock (its staging is live).
    """
    base = Path(root)
    try:
        with writer_lock(base, timeout=0):
            return recover_locked(base)
    except CatalogBusyError:
        return []


_TMP_NAME = re.compile(r"^\.(?P<name>.+)\.(?:[a-z]+-)?(?P<pid>\d+)(?:-[0-9a-f]+)?\.tmp$")


def pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def recover_locked(
    base: Path, lock_root: Path | None = None, *, timeout: float | None = DEFAULT_LOCK_TIMEOUT
) -> list[str]:
    """Under the writer lock: finish dead commits, drop dead staging and temporary files
    (waiting up to ``timeout`` s for the readers there are)."""
    with readers_excluded(lock_root or base, timeout):
        done = roll_forward(base)
    for folder in staging_folders(base):  # no journal: a dead writer's half-staged work
        shutil.rmtree(folder, ignore_errors=True)
        done.append(f"discarded {folder.name}")
    drop_empty_staging(base)
    if base.is_dir():
        for leftover in base.iterdir():  # .catalog.json.<pid>-<id>.tmp of a killed write
            match = _TMP_NAME.match(leftover.name)
            if match and leftover.is_file() and not pid_alive(int(match["pid"])):
                leftover.unlink(missing_ok=True)
                done.append(f"removed {leftover.name}")
    return done
