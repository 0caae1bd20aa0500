"""The bearer-token checks, standard library only: the connection guards
(:mod:`service.server.connections`) compare a token without loading the app."""

from __future__ import annotations

import hmac
from collections.abc import Sequence


def token_index(authorization: str | bytes | None, tokens: Sequence[str]) -> int | None:
    """Which of ``tokens`` an ``Authorization`` header value carries as its bearer token."""
    if isinstance(authorization, bytes):
        authorization = authorization.decode("latin-1")
    scheme, _, value = (authorization or "").partition(" ")
    if scheme.lower() != "bearer" or not value.strip():
        return None
    given = value.strip().encode()
    found = None
    for i, token in enumerate(tokens):  # every one compared: the time says nothing of which
        if hmac.compare_digest(given, token.encode()) and found is None:
            found = i
    return found


def token_problem(authorization: str | None, tokens: Sequence[str]) -> str | None:
    """Why an ``Authorization`` header value carries none of ``tokens`` (None when it does)."""
    scheme, _, value = (authorization or "").partition(" ")
    if scheme.lower() != "bearer" or not value:
        return "missing bearer token: send the header 'Authorization: Bearer <token>'"
    if token_index(authorization, tokens) is None:
        return "wrong bearer token: send the token the server was started with (GRASP_TOKEN)"
    return None
