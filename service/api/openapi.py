"""The API document: FastAPI's, plus what the code checks that FastAPI cannot see.

``POST /views`` reads its body itself (off the event loop, :mod:`service.intake.parsing`), so the
document gets the ViewIn schema added, with ViewIn's own model validator written as JSON Schema
(exactly one of points, depth with intrinsics, or grid; a support plane needs a camera pose, an
object label a mask; points in front of the camera) and the limits of this server's settings;
every operation with query parameters documents the 400 of a parameter given twice.
"""

from __future__ import annotations

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from service.api.schemas import ViewIn
from service.intake.inputs import MAX_COORDINATE_M
from service.settings import Settings


def document(app: FastAPI) -> dict:
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
        _repeated_query(document)
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


def _repeated_query(document: dict) -> None:
    """Every operation with query parameters may answer 400: one of them given twice
    (:class:`service.api.middleware.QueryOnce`)."""
    for methods in document.get("paths", {}).values():
        for operation in methods.values():
            if any(p.get("in") == "query" for p in operation.get("parameters", [])):
                operation.setdefault("responses", {}).setdefault("400", {
                    "description": "a query parameter given more than once (named in detail)",
                    "content": {"application/json": {"schema": {
                        "type": "object", "properties": {"detail": {"type": "string"}}}}}})


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
