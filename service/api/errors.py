"""Every exception a client can cause, answered as a 4xx with a ``detail`` saying what was
expected (422 details are lists of ``{loc, msg, type}`` as FastAPI's own), never a 500.
:func:`install` adds the handlers to an app."""

from __future__ import annotations

from fastapi import FastAPI, Request, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import compile_path

from completion.mesh import EmptyMeshError
from completion.stream import NoObjectError
from service.engine.pipeline import ModelMismatch, TooManyViews
from service.engine.planning import ClientGone, PlannerBusy
from service.intake.inputs import InputError
from service.intake.parsing import BODY_EXPECTED, capped, field_hint
from service.store.base import ConcurrentUpdate, SessionNotFound, StoreFull


def install(app: FastAPI) -> None:
    """The handlers of this module on ``app``."""
    for exc_type, code in _STATUS.items():
        app.add_exception_handler(exc_type, _message_handler(code))
    app.add_exception_handler(InputError, _input_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)


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
    """FastAPI's 422, without echoing the (possibly megabytes of) input back, with what was
    expected where the body is not a JSON object at all, and at most
    :data:`service.intake.parsing.MAX_ERRORS` errors (then a count of the rest)."""
    detail = []
    for e in capped(list(exc.errors())):
        kind = e.get("type", "")
        loc = list(e.get("loc", ()))
        msg = e.get("msg", "")
        whole = loc == ["body"] or (kind == "json_invalid" and len(loc) <= 2)
        if kind in _BODY_HINTS and loc[:1] == ["body"] and whole:
            msg = f"{msg}: {_BODY_HINTS[kind]}"  # loc keeps where JSON parsing stopped
        elif kind in ("model_type", "model_attributes_type", "dict_type") and len(loc) > 1:
            msg = f"{msg}: {field_hint(loc)}"
        detail.append({"loc": loc, "msg": msg[:1000], "type": kind})
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
        methods = _methods_of(request)
        if methods:
            headers = (headers or {}) | {"Allow": ", ".join(methods)}
    return JSONResponse({"detail": detail}, status_code=exc.status_code, headers=headers)


def _methods_of(request: Request) -> list[str]:
    """Every method the API document gives this request's path (upper case, sorted), its
    templates matched by Starlette's own path compiler."""
    methods: set[str] = set()
    for template, operations in request.app.openapi().get("paths", {}).items():
        regex, _, _ = compile_path(template)
        if regex.match(request.url.path):
            methods |= {m.upper() for m in operations}
    return sorted(methods)
