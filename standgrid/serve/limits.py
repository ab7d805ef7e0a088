"""Request bodies larger than a limit are refused with 413 before they are read in full."""

from __future__ import annotations

from typing import Any

from standgrid.serve.problems import problem_response

#: Default limit of a request body (a payload cloud of a few million points fits).
DEFAULT_MAX_BODY = 64 * 1024 * 1024


class BodyTooLarge(Exception):
    """Raised inside ``receive`` when a streamed body passes the limit."""


class BodyLimit:
    """ASGI middleware: ``Content-Length`` over ``max_bytes`` is refused at once; a chunked
    body is counted as it arrives and refused when it passes the limit."""

    def __init__(self, app: Any, max_bytes: int = DEFAULT_MAX_BODY) -> None:
        self.app = app
        self.max_bytes = int(max_bytes)

    def _refuse(self, scope: dict[str, Any]) -> Any:
        return problem_response(
            413, f"request body larger than {self.max_bytes} bytes", instance=scope.get("path")
        )

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers") or [])
        length = headers.get(b"content-length")
        if length is not None:
            try:
                declared = int(length)
            except ValueError:
                declared = -1
            if declared < 0:
                response = problem_response(
                    400, "invalid Content-Length", instance=scope.get("path")
                )
                await response(scope, receive, send)
                return
            if declared > self.max_bytes:
                await self._refuse(scope)(scope, receive, send)
                return
        seen = 0
        started = False

        async def counted_receive() -> dict[str, Any]:
            nonlocal seen
            message: dict[str, Any] = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.max_bytes:
                    raise BodyTooLarge
            return message

        async def tracked_send(message: dict[str, Any]) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counted_receive, tracked_send)
        except BodyTooLarge:
            if not started:
                await self._refuse(scope)(scope, receive, send)
