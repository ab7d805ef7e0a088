"""The live event stream, ``GET /events`` (Server-Sent Events): what the robots' writes
changed, as the server stores it.

:class:`EventHub` is one per app, in the server's process: the ingest routes publish to it
once a write is durable (never a payload that is not stored), in their mission's turn, so a
mission's events come in the order its writes were stored. Each event has an id
(``<run>-<n>``, ``run`` new at each server start); the last :data:`RING_EVENTS` are kept
in memory, so a client that reconnects with ``Last-Event-ID`` gets what it missed, or a
``resync`` event when that is no longer held (or the server restarted). Each client reads
from its own queue of at most :data:`CLIENT_QUEUE` events: a client that does not keep up
loses its queue and gets ``resync`` (publishing never waits for a client). Comments are
sent as heartbeats; the streams end when the server stops (:meth:`EventHub.close`, called
by :class:`~standgrid.serve.server.Server` as it shuts down, before it waits for requests).
"""

from __future__ import annotations

import asyncio
import json
import secrets
from collections import deque
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import APIRouter, Header, Request
from fastapi.responses import StreamingResponse

from standgrid.serve.problems import Problem

#: Events kept for clients that reconnect (``Last-Event-ID``).
RING_EVENTS = 1024
#: Events waiting for one client at most; beyond, its queue is dropped for a ``resync``.
CLIENT_QUEUE = 256
#: Clients streaming at once at most (another is refused with 503).
MAX_CLIENTS = 64
#: Seconds between heartbeats (SSE comments) on an idle stream.
HEARTBEAT_S = 15.0
#: Milliseconds a browser waits before it reconnects (the stream's ``retry``).
RETRY_MS = 2000
#: The types of event, in the order of a mission's life.
EVENT_TYPES = ("mission", "payload", "trajectory", "tiled", "resync")
#: The type of the event each stream starts with (no id; not kept): the client is subscribed,
#: and ``last`` is the id of the newest event published before (null: none yet).
HELLO = "hello"

router = APIRouter(tags=["Live events"])


@dataclass(frozen=True)
class Event:
    """One published event: its id, type and data (JSON values)."""

    id: str
    type: str
    data: dict[str, Any]

    def encode(self) -> bytes:
        """The event as SSE text (one ``data`` line: JSON has no raw newline)."""
        text = json.dumps(self.data, separators=(",", ":"), allow_nan=False)
        return f"id: {self.id}\nevent: {self.type}\ndata: {text}\n\n".encode()


class _Closed:
    """What a client's queue receives when the server stops."""


CLOSED = _Closed()


class Subscriber:
    """One client's queue of events (bounded; see :meth:`EventHub.publish`)."""

    def __init__(self, size: int) -> None:
        self.queue: asyncio.Queue[Event | _Closed] = asyncio.Queue(size)
        self.dropped = 0


class EventHub:
    """The app's events: published by the ingest routes, streamed to every subscriber. Used
    from the server's event loop only (no locks)."""

    def __init__(
        self, ring: int = RING_EVENTS, queue: int = CLIENT_QUEUE, max_clients: int = MAX_CLIENTS
    ) -> None:
        self.run = secrets.token_hex(4)
        self.ring: deque[Event] = deque(maxlen=ring)
        self.queue_size = queue
        self.max_clients = max_clients
        self.subscribers: set[Subscriber] = set()
        self.closed = False
        self._count = 0
        self._latest: dict[tuple[str, str], dict[str, Any]] = {}

    def publish(self, kind: str, data: dict[str, Any]) -> Event:
        """Keep and send an event. A client whose queue is full loses it (and what it held)
        and gets a ``resync`` instead: it reloads the state rather than stall the others."""
        if kind not in EVENT_TYPES:
            raise ValueError(f"unknown event type {kind!r}")
        self._count += 1
        event = Event(f"{self.run}-{self._count}", kind, data)
        self.ring.append(event)
        for sub in self.subscribers:
            try:
                sub.queue.put_nowait(event)
            except asyncio.QueueFull:
                self._drop(sub, "overflow", event)
        return event

    def publish_changed(self, kind: str, key: str, data: dict[str, Any]) -> Event | None:
        """:meth:`publish` unless the last event of this ``kind`` and ``key`` (a mission's
        trajectory) said the same (None then); the last :data:`RING_EVENTS` keys are kept."""
        last = self._latest.pop((kind, key), None)
        self._latest[(kind, key)] = data
        while len(self._latest) > RING_EVENTS:
            del self._latest[next(iter(self._latest))]
        return None if last == data else self.publish(kind, data)

    def _drop(self, sub: Subscriber, reason: str, last: Event | None) -> None:
        """Empty the client's queue and leave a ``resync`` there (ids after ``last``)."""
        while not sub.queue.empty():
            sub.queue.get_nowait()
        sub.dropped += 1
        sub.queue.put_nowait(self._resync(reason, last))

    def _resync(self, reason: str, last: Event | None) -> Event:
        """A ``resync`` event (not kept): the client reloads the catalog's state; its id is
        that of ``last`` (the newest event it stands for), so a reconnect goes on from it."""
        ident = last.id if last is not None else f"{self.run}-{self._count}"
        return Event(ident, "resync", {"reason": reason})

    def check_room(self) -> None:
        """A 503 problem when :attr:`max_clients` clients stream already."""
        if len(self.subscribers) >= self.max_clients:
            raise Problem(503, f"{self.max_clients} clients stream events already: try later")

    def subscribe(self, last_event_id: str | None = None) -> Subscriber:
        """A new client's queue, holding the events after ``last_event_id`` (a reconnect),
        or a ``resync`` when they are no longer all kept or the id is of another run."""
        self.check_room()
        sub = Subscriber(self.queue_size)
        if last_event_id:
            missed = self._since(last_event_id)
            if missed is None:
                sub.queue.put_nowait(self._resync("gap", self.ring[-1] if self.ring else None))
            elif len(missed) > self.queue_size:
                sub.queue.put_nowait(self._resync("overflow", missed[-1]))
            else:
                for event in missed:
                    sub.queue.put_nowait(event)
        if not self.closed:
            self.subscribers.add(sub)
        return sub

    def _since(self, last_event_id: str) -> list[Event] | None:
        """The kept events after ``last_event_id``; None when some are no longer kept, or
        the id is not one of this run."""
        run, _, number = last_event_id.strip().rpartition("-")
        digits = number.isascii() and number.isdigit()  # not '²': int() would refuse it
        if run != self.run or not digits or int(number) > self._count:
            return None
        after = int(number)
        oldest = self._count - len(self.ring) + 1  # the number of ring[0]
        if after + 1 < oldest:
            return None
        return list(self.ring)[after + 1 - oldest :]

    def unsubscribe(self, sub: Subscriber) -> None:
        self.subscribers.discard(sub)

    def close(self) -> None:
        """End every stream (the server stops); later subscribers end at once."""
        self.closed = True
        for sub in self.subscribers:
            while sub.queue.full():
                sub.queue.get_nowait()
            sub.queue.put_nowait(CLOSED)
        self.subscribers.clear()


async def _stream(hub: EventHub, sub: Subscriber, heartbeat: float) -> AsyncIterator[bytes]:
    """The SSE text of one subscribed client, until the server stops or the client goes
    (it is unsubscribed then, also when the response never started)."""
    last = hub.ring[-1].id if hub.ring else None
    try:
        hello = json.dumps({"last": last, "kept": len(hub.ring)})
        yield f"retry: {RETRY_MS}\nevent: {HELLO}\ndata: {hello}\n\n".encode()
        while not hub.closed or not sub.queue.empty():
            try:
                item = await asyncio.wait_for(sub.queue.get(), heartbeat)
            except TimeoutError:
                yield b": heartbeat\n\n"
                continue
            if isinstance(item, _Closed):
                return
            yield item.encode()
    finally:
        hub.unsubscribe(sub)


@router.get(
    "/events",
    summary="Live events (Server-Sent Events): missions created, payloads stored, "
    "trajectories grown, increments tiled",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}}},
)
async def events(
    request: Request,
    last_event_id: Annotated[
        str | None, Header(description="the id of the last event received (a reconnect)")
    ] = None,
) -> StreamingResponse:
    hub: EventHub = request.app.state.events
    sub = hub.subscribe(last_event_id)  # here, so a full hub is a 503 before any header
    heartbeat: float = getattr(request.app.state, "event_heartbeat", HEARTBEAT_S)
    return StreamingResponse(
        _stream(hub, sub, heartbeat),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
