"""One progress protocol for every stage: ``track`` long loops, ``status`` one-line news."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Protocol, TypeVar

T = TypeVar("T")


class Progress(Protocol):
    """Reports a stage's progress; the CLI renders it on stderr (bars and lines)."""

    def track(self, items: Iterable[T], total: int, desc: str) -> Iterable[T]:
        """Yield ``items`` (``total`` of them, 0 when unknown), showing how far it got."""
        ...

    def status(self, message: str) -> None:
        """One line of news (what is being done, what was found)."""
        ...


class _Silent:
    def track(self, items: Iterable[T], total: int, desc: str) -> Iterable[T]:
        return items

    def status(self, message: str) -> None:
        return None


#: Reports nothing (the default of every stage called from a script).
SILENT: Progress = _Silent()


@dataclass(frozen=True)
class CallbackProgress:
    """A :class:`Progress` from two callables (``wrap(items, total, desc)``, ``status(text)``)."""

    wrap: Callable[[Iterable[object], int, str], Iterable[object]] | None = None
    on_status: Callable[[str], None] | None = None

    def track(self, items: Iterable[T], total: int, desc: str) -> Iterable[T]:
        if self.wrap is None:
            return items
        return self.wrap(items, total, desc)  # type: ignore[return-value]

    def status(self, message: str) -> None:
        if self.on_status is not None:
            self.on_status(message)
