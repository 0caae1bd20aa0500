"""What the routes depend on: the running service's parts, and the bearer-token check."""

from __future__ import annotations

import hmac
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Annotated, TypeVar

import anyio.to_thread
from anyio import CapacityLimiter
from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.parsing import BodyParser
from service.pipeline import Pipeline
from service.planning import Planner
from service.sessions import SessionLocks
from service.settings import Settings

T = TypeVar("T")


@dataclass
class Services:
    """Everything the lifespan builds: settings, the pipeline, the planner, the thread limit."""

    settings: Settings
    pipeline: Pipeline
    inference: CapacityLimiter  # model steps and completions running at once
    planner: Planner  # grasp plans, in worker processes or threads
    locks: SessionLocks  # POST /views of one session, one after the other
    parser: BodyParser  # POST /views bodies, parsed off the event loop

    async def infer(self, fn: Callable[..., T], *args, **kwargs) -> T:
        """Run blocking model work in a worker thread, at most ``inference_workers`` at once."""
        return await anyio.to_thread.run_sync(partial(fn, *args, **kwargs), limiter=self.inference)

    async def io(self, fn: Callable[..., T], *args, **kwargs) -> T:
        """Run a quick store call in a worker thread, without queueing behind the model."""
        return await anyio.to_thread.run_sync(partial(fn, *args, **kwargs))


def get_services(request: Request) -> Services:
    return request.app.state.services


ServicesDep = Annotated[Services, Depends(get_services)]

_bearer = HTTPBearer(auto_error=False, description="needed when GRASP_TOKEN is set")


def token_problem(authorization: str | None, token: str) -> str | None:
    """Why an ``Authorization`` header value does not carry ``token`` (None when it does)."""
    scheme, _, value = (authorization or "").partition(" ")
    if scheme.lower() != "bearer" or not value:
        return "missing bearer token: send the header 'Authorization: Bearer <token>'"
    if not hmac.compare_digest(value.strip().encode(), token.encode()):
        return "wrong bearer token: send the token the server was started with (GRASP_TOKEN)"
    return None


def require_token(
    services: ServicesDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """401 unless the request carries ``Authorization: Bearer <GRASP_TOKEN>`` (when one is set).

    :class:`service.app.TokenGate` has already checked this before the body was read; this
    dependency declares the scheme in the OpenAPI document and guards in-process callers."""
    token = services.settings.token
    if token is None:
        return
    header = None if credentials is None else f"{credentials.scheme} {credentials.credentials}"
    problem = token_problem(header, token.get_secret_value())
    if problem is not None:
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED, problem, headers={"WWW-Authenticate": "Bearer"}
        )
