"""``POST /views``: one view into a session (a new one without ``session_id``), applied once
per ``Idempotency-Key``."""

from __future__ import annotations

from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, Depends, Header, Request

from service.api.depends import ServicesDep, require_token, responses
from service.api.schemas import ViewOut
from service.intake.parsing import ParsedView

router = APIRouter(dependencies=[Depends(require_token)], responses=responses(401, 413, 422))


async def view_body(request: Request, services: ServicesDep) -> AsyncIterator[ParsedView]:
    """The body, read under the size limit, then parsed, validated and decoded off the event
    loop (:mod:`service.intake.parsing`), its memory reserved until the answer is out
    (:mod:`service.intake.memory`)."""
    async with services.parser.view(request) as parsed:
        yield parsed


#: ``POST /views`` reads its body itself; the document still shows it as a ViewIn.
_VIEW_BODY = {
    "requestBody": {
        "required": True,
        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ViewIn"}}},
    }
}


IdempotencyKey = Annotated[
    str | None,
    Header(max_length=128, pattern=r"^[!-~]+$",
           description="a key the client chooses per view (a UUID), sent again with every retry "
           "of it: a view whose key was seen is not applied twice, its first answer comes back "
           "(kept as long as a session lives)"),
]


@router.post(
    "/views",
    response_model=ViewOut,
    responses=responses(400, 404, 409, 503),
    openapi_extra=_VIEW_BODY,
)
async def post_view(
    parsed: Annotated[ParsedView, Depends(view_body)],
    services: ServicesDep,
    idempotency_key: IdempotencyKey = None,
) -> ViewOut:
    """Add one view to a session (a new one when ``session_id`` is absent). The body is a
    ``ViewIn``: exactly one of ``points``, ``depth`` with ``intrinsics``, or ``grid``. With an
    ``Idempotency-Key`` header, a view sent again with the same key is not applied again: it
    gets the first answer."""
    if idempotency_key is None:
        return await _apply_view(parsed, services)
    async with services.exclusive(f"idempotency:{idempotency_key}"):
        kept = await services.io(services.pipeline.store.recall, idempotency_key)
        if kept is not None:
            return ViewOut.model_validate_json(kept)
        out = await _apply_view(parsed, services)
        await services.io(services.pipeline.store.remember, idempotency_key,
                          out.model_dump_json())
        return out


async def _apply_view(parsed: ParsedView, services) -> ViewOut:
    view, session_id = parsed.view, parsed.session_id
    if session_id is None:
        session_id, result = await services.infer(services.pipeline.add_view, None, view)
    else:  # the session's lock is awaited here, outside the inference slots; 503 if it stays
        async with services.exclusive(session_id):
            session_id, result = await services.infer(services.pipeline.add_view, session_id, view)
    return ViewOut(
        session_id=session_id,
        view_index=result.view_index,
        observed_voxels=result.observed_voxels,
        occupied_voxels=result.occupied_voxels,
        completion="registered" if result.registered else "memory",
    )
