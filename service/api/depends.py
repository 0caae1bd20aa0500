"""What the routes depend on: the running service's parts, the bearer token, a session id in the
path, and the planning query that ``GET /grasp`` and the inspector's ``scene.glb`` share
(:class:`PlanQuery`, one declaration of its parameters).

No ``from __future__ import annotations`` here: FastAPI reads :class:`PlanQuery`'s field types
from the dataclass at run time.
"""

from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, HTTPException, Path, Query, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from grasp.defaults import HOLD_THRESHOLD
from grasp_client.wire import SupportPlane
from service.api.auth import token_index, token_problem
from service.api.schemas import ErrorOut
from service.engine.pipeline import Pipeline
from service.services import Services
from service.store.owned import client_id

_WHY = {
    400: "the body could not be decoded as text",
    401: "missing or wrong bearer token (when GRASP_TOKEN is set)",
    404: "unknown or expired session",
    409: "the session cannot answer yet (no object seen, empty completion, other model)",
    413: "request body over GRASP_MAX_BODY_BYTES",
    422: "invalid input; the detail says what was expected",
    503: "the session store is full, too many grasp plans are waiting, or another replica "
    "held the session's lock for two leases (Retry-After)",
}



def responses(*codes: int) -> dict:
    """The OpenAPI ``responses`` of these error codes (each an :class:`ErrorOut`)."""
    return {code: {"model": ErrorOut, "description": _WHY[code]} for code in codes}


PathId = Annotated[str, Path(min_length=1, max_length=128, description="from POST /views")]


def get_services(request: Request) -> Services:
    return request.app.state.services


ServicesDep = Annotated[Services, Depends(get_services)]

_bearer = HTTPBearer(auto_error=False, description="needed when GRASP_TOKEN is set")


def require_token(
    services: ServicesDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> str:
    """401 unless the request carries ``Authorization: Bearer <GRASP_TOKEN>`` (when one is set);
    the client it is (:func:`service.store.owned.client_id`, "" without tokens).

    :class:`service.api.middleware.TokenGate` has already checked this before the body was read;
    this dependency declares the scheme in the OpenAPI document and guards in-process callers."""
    tokens = services.settings.tokens()
    if not tokens:
        return client_id(None)
    header = None if credentials is None else f"{credentials.scheme} {credentials.credentials}"
    problem = token_problem(header, tokens)
    if problem is not None:
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED, problem, headers={"WWW-Authenticate": "Bearer"}
        )
    return client_id(tokens[token_index(header, tokens)])


#: The client a request is (a route-level ``require_token``: FastAPI runs it once a request).
ClientDep = Annotated[str, Depends(require_token)]


def owned_sessions(services: ServicesDep, client: ClientDep) -> Pipeline:
    """The pipeline on the request's client's sessions alone (another's are 404)."""
    return services.pipeline.for_owner(client)


SessionsDep = Annotated[Pipeline, Depends(owned_sessions)]


TopK = Annotated[int, Query(ge=1, le=64, description="grasps returned, best first")]
NCandidates = Annotated[
    int | None, Query(ge=1, description="candidates tried (default GRASP_N_CANDIDATES)")
]
VerifyQuery = Annotated[
    int | None,
    Query(ge=0, description="lift-test at most this many of the best grasps on the completion, "
          "standing on the support plane, before answering; the first that holds in every trial "
          "comes first, and each grasp says what its trials saw (default GRASP_VERIFY, at most "
          "GRASP_MAX_VERIFY; about 0.5 s a trial, spread over the planner's processes)"),
]
SupportPlaneQuery = Annotated[
    str | None,
    Query(
        max_length=200,
        description="the surface the object rests on, 'nx,ny,nz,d' in the world frame "
        "(n·x + d = 0, n pointing up, not zero; metres): the session keeps it (as if given "
        "on POST /views), the completion is cut at it and the hand treats it as an obstacle. "
        "Needs camera poses on the views.",
        examples=["0,0,1,0"],
        json_schema_extra={"pattern": SupportPlane.PATTERN.pattern},
    ),
]


MinHoldQuery = Annotated[
    float,
    Query(ge=0.0, le=1.0, description="on a table, a force-closure grasp the lift model gives a "
          "lower chance to hold is a failure that says so; lower it (0.3) to get such grasps "
          "back, each with its hold_probability, and decide yourself (or verify them)"),
]


@dataclass
class PlanQuery:
    """``GET /grasp``'s planning parameters (a FastAPI dependency: each field a query
    parameter)."""

    top_k: TopK = 1
    n_candidates: NCandidates = None
    support_plane: SupportPlaneQuery = None
    verify: VerifyQuery = None
    min_hold: MinHoldQuery = HOLD_THRESHOLD


@dataclass
class SceneQuery(PlanQuery):
    """The inspector's ``scene.glb``: the same parameters, five grasps by default."""

    top_k: TopK = 5
