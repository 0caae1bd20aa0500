"""ASGI middleware in front of every route: the token checked before a body is read
(:class:`TokenGate`), the body's size limit (:class:`BodyLimit`), and query parameters given
once (:class:`QueryOnce`)."""

from __future__ import annotations

import logging
import re
from collections import Counter
from collections.abc import Sequence
from urllib.parse import parse_qsl

from fastapi import HTTPException, status
from fastapi.responses import JSONResponse
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.auth import token_problem

log = logging.getLogger(__name__)

#: Paths that need no token: liveness, the API documents, the inspector page and its assets.
PUBLIC_PATHS = re.compile(
    r"^/(healthz|docs(/.*)?|redoc|openapi\.json|static/inspector/.*|sessions/[^/]+/view)$"
)


class TokenGate:
    """401 before the request body is read, when ``GRASP_TOKEN`` is set and the request does
    not carry it (a tokenless 30 MB upload is refused without parsing or keeping a byte of it).

    An answer sent before the body was read says ``Connection: close``: the server
    (:mod:`service.server.connections`) discards the rest of the body, within bounds, then closes,
    so a client that reads only after sending (urllib, requests) sees the answer and not a reset."""

    def __init__(self, app: ASGIApp, *, tokens: Sequence[str]) -> None:
        self.app = app
        self.tokens = tuple(tokens)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not self.tokens or PUBLIC_PATHS.match(scope["path"]):
            await self.app(scope, receive, send)
            return
        header = next(
            (v.decode("latin-1") for k, v in scope["headers"] if k == b"authorization"), None
        )
        problem = token_problem(header, self.tokens)
        if problem is None:
            await self.app(scope, receive, send)
            return
        response = JSONResponse(
            {"detail": problem},
            status.HTTP_401_UNAUTHORIZED,
            headers={"WWW-Authenticate": "Bearer", "Connection": "close"},
        )
        await response(scope, receive, send)


class BodyLimit:
    """413 for request bodies over ``max_bytes``, by Content-Length or while streaming; with
    ``Connection: close``, as :class:`TokenGate`'s early answer. A body that stops coming (the
    client left, or took over ``GRASP_BODY_TIMEOUT_S``) ends the request quietly: there is no
    one to answer, and it is not the server's error."""

    def __init__(self, app: ASGIApp, *, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    def _message(self) -> str:
        return f"request body over the limit of {self.max_bytes} bytes (GRASP_MAX_BODY_BYTES)"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        for name, value in scope["headers"]:
            if name == b"content-length" and value.isdigit() and int(value) > self.max_bytes:
                response = JSONResponse(
                    {"detail": self._message()},
                    status.HTTP_413_CONTENT_TOO_LARGE,
                    headers={"Connection": "close"},
                )
                await response(scope, receive, send)
                return
        received = 0
        gone = False

        async def limited() -> Message:
            nonlocal received, gone
            message = await receive()
            gone = message["type"] == "http.disconnect"
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise HTTPException(
                        status.HTTP_413_CONTENT_TOO_LARGE,
                        self._message(),
                        headers={"Connection": "close"},
                    )
            return message

        try:
            await self.app(scope, limited, send)
        except ClientDisconnect:
            if not gone:
                raise
            log.info("%s %s: the client left before its body was complete",
                     scope["method"], scope["path"])  # fmt: skip


class QueryOnce:
    """400 for a query parameter given more than once (``?session_id=A&session_id=B``), naming
    it: a framework keeps one of them silently (the last), so the request would act on a session
    the client may not have meant. No route takes a list in its query."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        query = scope.get("query_string", b"") if scope["type"] == "http" else b""
        if query:
            pairs = parse_qsl(query.decode("latin-1"), keep_blank_values=True)
            repeated = sorted(name for name, n in Counter(k for k, _ in pairs).items() if n > 1)
            if repeated:
                names = ", ".join(repeated[:8]) + (", …" if len(repeated) > 8 else "")
                response = JSONResponse(
                    {"detail": f"query parameters given more than once: {names[:300]}; give "
                               "each once"},
                    status.HTTP_400_BAD_REQUEST,
                )
                await response(scope, receive, send)
                return
        await self.app(scope, receive, send)
