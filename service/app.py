"""The FastAPI app factory: settings in, app out; the model is loaded in the lifespan.

Errors: every exception a client can cause maps to a 4xx with a ``detail`` saying what was
expected (422 details are lists of ``{loc, msg, type}`` as FastAPI's own), never a 500.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from functools import partial

import anyio.to_thread
from anyio import CapacityLimiter
from fastapi import FastAPI, HTTPException, Request, status
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from completion.mesh import EmptyMeshError
from completion.stream import NoObjectError
from service import inspector  # its data routes join `router` on import
from service.deps import Services, token_problem
from service.inputs import MAX_COORDINATE_M, InputError
from service.memory import return_freed_memory
from service.parsing import BODY_EXPECTED, BodyParser, field_hint
from service.pipeline import ModelMismatch, Pipeline, TooManyViews
from service.planning import ClientGone, Planner, PlannerBusy
from service.routes import health_router, router
from service.schemas import ViewIn
from service.sessions import SessionLocks, open_store
from service.settings import Settings
from service.store import ConcurrentUpdate, SessionNotFound, Store, StoreFull

log = logging.getLogger(__name__)

#: Seconds between sweeps that delete expired sessions (at most; shorter for short TTLs).
PURGE_INTERVAL_S = 60.0


def create_app(settings: Settings | None = None) -> FastAPI:
    """The service; ``settings`` default to the ``GRASP_*`` environment."""
    settings = settings or Settings()
    app = FastAPI(
        title="mvp-grasp",
        summary="Stream depth views of an object, get a BarrettHand grasp on its completed shape",
        version="0.1.0",
        lifespan=_lifespan,
    )
    app.state.settings = settings
    app.include_router(router)
    app.include_router(health_router)
    inspector.mount(app)
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    token = None if settings.token is None else settings.token.get_secret_value()
    app.add_middleware(TokenGate, token=token)  # added last: runs first, before the body
    for exc_type, code in _STATUS.items():
        app.add_exception_handler(exc_type, _message_handler(code))
    app.add_exception_handler(InputError, _input_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.openapi = partial(_openapi, app)
    return app


def _openapi(app: FastAPI) -> dict:
    """FastAPI's document, plus the ViewIn schema that ``POST /views`` refers to (the route
    parses its body itself, off the event loop)."""
    if app.openapi_schema is None:
        document = get_openapi(
            title=app.title,
            version=app.version,
            summary=app.summary,
            routes=app.routes,
        )
        components = document.setdefault("components", {})
        schemas = components.setdefault("schemas", {})
        view = ViewIn.model_json_schema(ref_template="#/components/schemas/{model}")
        schemas.update(view.pop("$defs", {}))
        schemas["ViewIn"] = _view_schema(view, app.state.settings)
        _match_settings(document, app.state.settings)
        app.openapi_schema = document
    return app.openapi_schema


def _null(*names: str) -> dict:
    return {name: {"type": "null"} for name in names}


def _view_schema(view: dict, settings: Settings) -> dict:
    """ViewIn's own model validator, written as JSON Schema: exactly one of points, depth with
    intrinsics (and an optional mask), or grid; absent and null are the same; a support_plane
    needs a camera_pose, an object_label a mask. Points: at most ``max_points``, within
    ±MAX_COORDINATE_M, in front of the camera (z > 0)."""
    view["oneOf"] = [
        {"required": ["points"], "properties": {"points": {"type": "array"}}
         | _null("depth", "intrinsics", "mask", "grid")},
        {"required": ["depth", "intrinsics"],
         "properties": {"depth": {"type": "object"}, "intrinsics": {"type": "object"}}
         | _null("points", "grid")},
        {"required": ["grid"], "properties": {"grid": {"type": "object"}}
         | _null("points", "depth", "intrinsics", "mask")},
    ]  # fmt: skip
    view["allOf"] = [  # "if given (not null), then that one too"
        {"if": {"required": [field], "properties": {field: {"not": {"type": "null"}}}},
         "then": {"required": [needs], "properties": {needs: {"not": {"type": "null"}}}}}
        for field, needs in (("support_plane", "camera_pose"), ("object_label", "mask"))
    ]
    coordinate = {"type": "number", "minimum": -MAX_COORDINATE_M, "maximum": MAX_COORDINATE_M}
    point = {
        "type": "array",
        "prefixItems": [coordinate, coordinate, coordinate | {"exclusiveMinimum": 0}],
        "items": False,
        "minItems": 3,
        "maxItems": 3,
    }
    for option in view["properties"]["points"].get("anyOf", []):
        if option.get("type") == "array":
            option["items"] = point
            option["maxItems"] = settings.max_points
    return view


def _match_settings(document: dict, settings: Settings) -> None:
    """What the document says depends on this server's settings: the bearer scheme only when
    a token is required; n_candidates up to GRASP_MAX_CANDIDATES."""
    for methods in document.get("paths", {}).values():
        for operation in methods.values():
            if settings.token is None:
                operation.pop("security", None)
            for parameter in operation.get("parameters", []):
                if parameter["name"] != "n_candidates":
                    continue
                for option in parameter["schema"].get("anyOf", [parameter["schema"]]):
                    if option.get("type") == "integer":
                        option["maximum"] = settings.max_candidates
    if settings.token is None:
        document.get("components", {}).pop("securitySchemes", None)


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    import torch

    from completion.model import load_model

    settings: Settings = app.state.settings
    torch.set_num_threads(settings.torch_threads)
    return_freed_memory()  # big arrays given back to the system when freed (service.memory)
    model = await anyio.to_thread.run_sync(load_model, settings.model)
    store = await anyio.to_thread.run_sync(open_store, settings)
    pipeline = await anyio.to_thread.run_sync(
        lambda: Pipeline(model, store, model_name=settings.model, max_views=settings.max_views)
    )
    app.state.services = Services(
        settings=settings,
        pipeline=pipeline,
        inference=CapacityLimiter(settings.inference_workers),
        planner=Planner(
            settings.planning_workers,
            processes=settings.planning_processes,
            queue=settings.planning_queue,
            cache=settings.plan_cache,
            budget=settings.plan_budget,
        ),
        locks=SessionLocks(),
        parser=BodyParser(
            settings.inference_workers,
            max_body_bytes=settings.max_body_bytes,
            body_memory=settings.body_memory_bytes,
            decode_memory=settings.decode_memory_bytes,
            memory_wait_s=settings.memory_wait_s,
            max_image_pixels=settings.max_image_pixels,
            max_points=settings.max_points,
            max_depth_median_m=settings.max_depth_median_m,
            max_point_distance_m=settings.max_point_distance_m,
            at_once=settings.max_parsing,
        ),
    )
    log.info("model %s (weights %s), store %s", settings.model, pipeline.model_id, store.where)
    app.state.services.planner.warm_up()
    sweeper = asyncio.create_task(_purge_expired(store))
    try:
        yield
    finally:
        sweeper.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await sweeper
        await anyio.to_thread.run_sync(app.state.services.planner.close)
        app.state.services.parser.close()
        store.close()


async def _purge_expired(store: Store) -> None:
    interval = min(PURGE_INTERVAL_S, store.ttl_s)
    while True:
        await asyncio.sleep(interval)
        try:
            await anyio.to_thread.run_sync(store.purge_expired)
        except Exception:  # a busy or broken store must not end the sweeps
            log.exception("purging expired sessions failed")


# ------------------------------------------------------------------------------- errors

_STATUS: dict[type[Exception], int] = {
    SessionNotFound: status.HTTP_404_NOT_FOUND,
    NoObjectError: status.HTTP_409_CONFLICT,
    EmptyMeshError: status.HTTP_409_CONFLICT,
    ModelMismatch: status.HTTP_409_CONFLICT,
    ConcurrentUpdate: status.HTTP_409_CONFLICT,
    TooManyViews: status.HTTP_409_CONFLICT,
    StoreFull: status.HTTP_503_SERVICE_UNAVAILABLE,
    PlannerBusy: status.HTTP_503_SERVICE_UNAVAILABLE,
    ClientGone: 499,  # nginx's "client closed request": nobody reads it
}
_HINTS: dict[type[Exception], str] = {
    NoObjectError: "; POST /views with a view that shows the object first",
    EmptyMeshError: "; nothing to mesh or grasp: add views that show the object",
}


def _message_handler(code: int):
    async def handler(request: Request, exc: Exception) -> JSONResponse:
        detail = str(exc) + _HINTS.get(type(exc), "")
        headers = None
        if code == status.HTTP_503_SERVICE_UNAVAILABLE:  # a busy planner frees up in seconds
            headers = {"Retry-After": "1" if isinstance(exc, PlannerBusy) else "60"}
        return JSONResponse({"detail": detail}, status_code=code, headers=headers)

    return handler


async def _input_error(request: Request, exc: InputError) -> JSONResponse:
    detail = [{"loc": list(exc.loc), "msg": exc.message, "type": "value_error"}]
    return JSONResponse({"detail": detail}, status_code=status.HTTP_422_UNPROCESSABLE_CONTENT)


#: Plain words for the errors that mean "this is not the JSON object expected".
_BODY_HINTS = {
    "json_invalid": "the body is not valid JSON: " + BODY_EXPECTED,
    "model_attributes_type": "the body is not a JSON object: " + BODY_EXPECTED,
    "model_type": "the body is not a JSON object: " + BODY_EXPECTED,
}


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    """FastAPI's 422, without echoing the (possibly megabytes of) input back, and with what
    was expected where the body is not a JSON object at all."""
    detail = []
    for e in exc.errors():
        kind = e.get("type", "")
        loc = list(e.get("loc", ()))
        msg = e.get("msg", "")
        whole = loc == ["body"] or (kind == "json_invalid" and len(loc) <= 2)
        if kind in _BODY_HINTS and loc[:1] == ["body"] and whole:
            msg = f"{msg}: {_BODY_HINTS[kind]}"  # loc keeps where JSON parsing stopped
        elif kind in ("model_type", "model_attributes_type", "dict_type") and len(loc) > 1:
            msg = f"{msg}: {field_hint(loc)}"
        detail.append({"loc": loc, "msg": msg, "type": kind})
    return JSONResponse({"detail": detail}, status_code=status.HTTP_422_UNPROCESSABLE_CONTENT)


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    """Starlette's own errors; its bare 400 for an undecodable body says what was expected, and
    a 405 lists every method of the path (Starlette names only the first route's)."""
    detail = exc.detail
    headers = exc.headers
    if exc.status_code == status.HTTP_400_BAD_REQUEST and detail == (
        "There was an error parsing the body"
    ):
        detail = "the body could not be decoded: " + BODY_EXPECTED
    if exc.status_code == status.HTTP_405_METHOD_NOT_ALLOWED:
        methods = _methods_of(request.app, request.url.path)
        if methods:
            headers = (headers or {}) | {"Allow": ", ".join(methods)}
    return JSONResponse({"detail": detail}, status_code=exc.status_code, headers=headers)


def _methods_of(app: FastAPI, path: str) -> list[str]:
    """Every method the API document gives ``path`` (upper case, sorted)."""
    methods: set[str] = set()
    for template, operations in app.openapi().get("paths", {}).items():
        pattern = re.sub(r"\\{[^/]+?\\}", "[^/]+", re.escape(template))
        if re.fullmatch(pattern, path):
            methods |= {m.upper() for m in operations}
    return sorted(methods)


#: Paths that need no token: liveness, the API documents, the inspector page and its assets.
PUBLIC_PATHS = re.compile(
    r"^/(healthz|docs(/.*)?|redoc|openapi\.json|static/inspector/.*|sessions/[^/]+/view)$"
)


class TokenGate:
    """401 before the request body is read, when ``GRASP_TOKEN`` is set and the request does
    not carry it (a tokenless 30 MB upload is refused without parsing or keeping a byte of it).

    An answer sent before the body was read says ``Connection: close``: the server
    (:mod:`service.connections`) discards the rest of the body, within bounds, then closes, so a
    client that reads only after sending (urllib, requests) sees the answer and not a reset."""

    def __init__(self, app: ASGIApp, *, token: str | None) -> None:
        self.app = app
        self.token = token

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or self.token is None or PUBLIC_PATHS.match(scope["path"]):
            await self.app(scope, receive, send)
            return
        header = next(
            (v.decode("latin-1") for k, v in scope["headers"] if k == b"authorization"), None
        )
        problem = token_problem(header, self.token)
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
