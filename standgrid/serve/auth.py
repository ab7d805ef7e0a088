"""Writes need a bearer token; reads are open.

The token comes from a file (``--token-file``) or the environment variable
:data:`TOKEN_ENV`. :class:`WriteGuard` (ASGI middleware) refuses every request with a write
method (anything but GET, HEAD, OPTIONS) before it reaches a route unless its
``Authorization: Bearer <token>`` matches, compared in constant time (``hmac.compare_digest``).
"""

from __future__ import annotations

import hmac
import os
from pathlib import Path
from typing import Any

from standgrid.errors import FormatError, StandgridError
from standgrid.serve.problems import problem_response

TOKEN_ENV = "STANDGRID_TOKEN"
READ_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
#: Shorter tokens are refused: they can be guessed.
MIN_TOKEN_LENGTH = 16


def load_token(token_file: str | os.PathLike[str] | None = None) -> str | None:
    """The write token: the file's content (stripped), else ``$STANDGRID_TOKEN``, else None."""
    if token_file is not None:
        path = Path(token_file)
        try:
            token = path.read_text(encoding="utf-8").strip()
        except OSError as exc:
            raise StandgridError(f"cannot read the token file ({exc.strerror})", path=path) from exc
        source: Path | None = path
    else:
        token = os.environ.get(TOKEN_ENV, "").strip()
        source = None
        if not token:
            return None
    if len(token) < MIN_TOKEN_LENGTH or any(c.isspace() for c in token):
        where = "the token file" if source else f"${TOKEN_ENV}"
        raise FormatError(
            f"{where}: a token is one word of at least {MIN_TOKEN_LENGTH} characters",
            path=source,
        )
    return token


def bearer_matches(header: str | None, token: str) -> bool:
    """Whether an ``Authorization`` header carries ``token`` (constant-time comparison)."""
    if not header:
        return False
    scheme, _, value = header.partition(" ")
    if scheme.lower() != "bearer":
        return False
    return hmac.compare_digest(value.strip().encode("utf-8"), token.encode("utf-8"))


class WriteGuard:
    """ASGI middleware: a write request without the right bearer token gets a 401 problem."""

    def __init__(self, app: Any, token: str | None) -> None:
        self.app = app
        self.token = token

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] != "http" or scope["method"] in READ_METHODS:
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers") or [])
        header = headers.get(b"authorization", b"").decode("latin-1") or None
        if self.token is not None and bearer_matches(header, self.token):
            await self.app(scope, receive, send)
            return
        detail = (
            "writes need 'Authorization: Bearer <token>' with the server's token"
            if self.token is not None
            else f"this server takes no writes: it was started without --token-file or ${TOKEN_ENV}"
        )
        response = problem_response(
            401, detail, instance=scope.get("path"), headers={"WWW-Authenticate": "Bearer"}
        )
        await response(scope, receive, send)
