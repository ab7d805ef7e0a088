"""uvicorn around the app: the URLs it really listens on, and a server in a thread (tests,
benchmarks)."""

from __future__ import annotations

import contextlib
import errno
import socket
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import uvicorn

from standgrid.errors import StandgridError

#: Seconds Ctrl-C waits for requests in flight before it cancels them (their worker
#: processes are then killed: a write is atomic, a commit cut short is recovered).
GRACEFUL_SHUTDOWN_S = 10


class AddressInUseError(StandgridError, OSError):
    """The address the service should listen on is taken (or cannot be bound)."""


def check_port_free(host: str, port: int) -> None:
    """Raise :class:`AddressInUseError` (one line naming ``host:port``) when nothing could
    listen there now; port 0 (any free port) always passes."""
    if port == 0:
        return
    shown = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise AddressInUseError(f"cannot listen on {shown}: unknown host ({exc.strerror})") from exc
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
        try:
            probe.bind(address)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise AddressInUseError(
                    f"{shown} is already in use (another server?): choose "
                    "another port with --port (0: any free port)"
                ) from exc
            raise AddressInUseError(f"cannot listen on {shown}: {exc.strerror}") from exc


def service_urls(base: str) -> dict[str, str]:
    """The entry points of a service listening at ``base`` (``http://host:port``)."""
    return {
        "service": f"{base}/",
        "ogc": f"{base}/ogc",
        "files": f"{base}/files",
        "missions": f"{base}/missions",
        "docs": f"{base}/docs",
    }


class Server(uvicorn.Server):
    """A uvicorn server that knows its bound address once started (port 0 = any free port)
    and calls ``on_started(base_url)`` then."""

    def __init__(
        self, config: uvicorn.Config, on_started: Callable[[str], None] | None = None
    ) -> None:
        super().__init__(config)
        self.base_url: str | None = None
        self._on_started = on_started

    async def startup(self, sockets: Any = None) -> None:
        await super().startup(sockets)
        if self.servers and self.servers[0].sockets:
            host, port = self.servers[0].sockets[0].getsockname()[:2]
            shown = f"[{host}]" if ":" in str(host) else host
            self.base_url = f"http://{shown}:{port}"
            if self._on_started is not None:
                self._on_started(self.base_url)

    async def shutdown(self, sockets: Any = None) -> None:
        """End the app's event streams first (:mod:`standgrid.serve.events`): uvicorn then
        waits only for the requests in flight, not for clients that would listen forever."""
        hub = getattr(getattr(self.config.app, "state", None), "events", None)
        if hub is not None:
            hub.close()
        await super().shutdown(sockets)


def config(app: Any, host: str, port: int, **options: Any) -> uvicorn.Config:
    """uvicorn settings of the service (no access log by default: stderr is for progress;
    Ctrl-C waits at most :data:`GRACEFUL_SHUTDOWN_S` for requests in flight)."""
    options.setdefault("log_level", "warning")
    options.setdefault("access_log", False)
    options.setdefault("timeout_graceful_shutdown", GRACEFUL_SHUTDOWN_S)
    return uvicorn.Config(app, host=host, port=port, **options)


@contextlib.contextmanager
def running(
    app: Any, host: str = "127.0.0.1", port: int = 0, timeout: float = 20.0, **options: Any
) -> Iterator[Server]:
    """The app served by a real uvicorn server in a thread, on a free port by default;
    stopped (and joined) on exit."""
    server = Server(config(app, host, port, **options))
    thread = threading.Thread(target=server.run, name="standgrid-serve", daemon=True)
    thread.start()
    deadline = time.monotonic() + timeout
    while server.base_url is None:
        if not thread.is_alive() or time.monotonic() > deadline:
            server.should_exit = True
            raise StandgridError(f"the server did not start on {host}:{port}")
        time.sleep(0.01)
    try:
        yield server
    finally:
        server.should_exit = True
        thread.join(timeout)
