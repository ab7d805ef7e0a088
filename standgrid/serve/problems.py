"""Every error of the service as an RFC 9457 problem document (``application/problem+json``).

:class:`Problem` is the one exception routes raise for an HTTP outcome; library errors
(:class:`~standgrid.errors.StandgridError`), FastAPI's validation errors and Starlette's
HTTP errors (404 for an unknown route, 405, ...) are turned into the same document by the
handlers :func:`install` registers.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from http import HTTPStatus
from typing import Any

from standgrid.errors import (
    CatalogBusyError,
    CatalogConflictError,
    EpochNotFoundError,
    InsufficientGnssError,
    NotGeoreferencedError,
    OutputExistsError,
    PayloadNotFoundError,
    StaleLayersError,
    StandgridError,
)
from standgrid.mission.live import LiveMissionConflictError

PROBLEM_JSON = "application/problem+json"
_log = logging.getLogger("standgrid.serve")


class Problem(StandgridError):
    """An HTTP error with a clear message: ``status``, ``detail`` and optional extra members."""

    def __init__(
        self, status: int, detail: str, *, headers: dict[str, str] | None = None, **extra: Any
    ) -> None:
        super().__init__(detail)
        self.status = int(status)
        self.detail = detail
        self.headers = headers or {}
        self.extra = extra


def status_of(exc: StandgridError) -> int:
    """The HTTP status a library error maps to (its builtin base says what went wrong)."""
    if isinstance(exc, Problem):
        return exc.status
    if isinstance(exc, CatalogBusyError):
        return 503
    conflicts = (
        LiveMissionConflictError | CatalogConflictError | OutputExistsError | StaleLayersError
    )
    if isinstance(exc, conflicts | NotGeoreferencedError | InsufficientGnssError):
        return 409  # (the last two: not yet, send GNSS fixes first)
    if isinstance(exc, EpochNotFoundError | PayloadNotFoundError | LookupError | FileNotFoundError):
        return 404
    if isinstance(exc, ValueError):
        return 400
    return 500


def problem_body(status: int, detail: str, instance: str | None = None, **extra: Any) -> dict:
    """The problem document: ``type`` about:blank, ``title`` the status phrase."""
    body: dict[str, Any] = {
        "type": "about:blank",
        "title": HTTPStatus(status).phrase,
        "status": status,
        "detail": detail,
    }
    if instance:
        body["instance"] = instance
    body.update(extra)
    return body


def problem_response(
    status: int,
    detail: str,
    *,
    instance: str | None = None,
    headers: Mapping[str, str] | None = None,
    **extra: Any,
) -> Any:
    from starlette.responses import JSONResponse

    return JSONResponse(
        problem_body(status, detail, instance, **extra),
        status_code=status,
        headers=dict(headers) if headers else None,
        media_type=PROBLEM_JSON,
    )


def install(app: Any) -> None:
    """Register the handlers that turn every error into a problem document."""
    from fastapi.exceptions import RequestValidationError
    from starlette.exceptions import HTTPException
    from starlette.requests import Request

    async def standgrid_error(request: Request, exc: Exception) -> Any:
        assert isinstance(exc, StandgridError)
        status = status_of(exc)
        if status >= 500:
            _log.error("%s %s failed: %s", request.method, request.url.path, exc, exc_info=exc)
        extra = exc.extra if isinstance(exc, Problem) else {}
        headers = exc.headers if isinstance(exc, Problem) else None
        # Library errors name server paths: clients get the message, not the file.
        detail = exc.detail if isinstance(exc, Problem) else f"{type(exc).__name__}: {exc.message}"
        return problem_response(status, detail, instance=request.url.path, headers=headers, **extra)

    async def http_error(request: Request, exc: Exception) -> Any:
        assert isinstance(exc, HTTPException)
        detail = exc.detail if isinstance(exc.detail, str) else HTTPStatus(exc.status_code).phrase
        return problem_response(
            exc.status_code, detail, instance=request.url.path, headers=exc.headers
        )

    async def validation_error(request: Request, exc: Exception) -> Any:
        assert isinstance(exc, RequestValidationError)
        errors = [
            {"where": ".".join(str(p) for p in e.get("loc", ())), "message": e.get("msg", "")}
            for e in exc.errors()
        ]
        text = "; ".join(f"{e['where']}: {e['message']}" for e in errors)
        return problem_response(
            400, f"invalid request: {text}", instance=request.url.path, errors=errors
        )

    async def unexpected(request: Request, exc: Exception) -> Any:
        _log.error("%s %s failed", request.method, request.url.path, exc_info=exc)
        return problem_response(
            500, f"internal error ({type(exc).__name__})", instance=request.url.path
        )

    app.add_exception_handler(StandgridError, standgrid_error)
    app.add_exception_handler(HTTPException, http_error)
    app.add_exception_handler(RequestValidationError, validation_error)
    app.add_exception_handler(Exception, unexpected)
