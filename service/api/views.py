"""``POST /views``: one view into a session (a new one without ``session_id``), applied once
per ``Idempotency-Key``."""

from __future__ import annotations

from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, Depends, Header, Request

from service.api.depends import ClientDep, ServicesDep, SessionsDep, require_token, responses
from service.api.schemas import ViewOut
from service.engine.pipeline import Pipeline
from service.intake.inputs import InputError
from service.intake.parsing import ParsedView
from service.store.base import KeptAnswer

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
           "(kept as long as a session lives, deleted with its session, the client's newest "
           "GRASP_MAX_ANSWERS); the same key with another body is a 422. Each client's keys are "
           "its own"),
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
    sessions: SessionsDep,
    client: ClientDep,
    idempotency_key: IdempotencyKey = None,
) -> ViewOut:
    """Add one view to a session (a new one when ``session_id`` is absent). The body is a
    ``ViewIn``: exactly one of ``points``, ``depth`` with ``intrinsics``, or ``grid``. With an
    ``Idempotency-Key`` header, a view sent again with the same key and body is not applied
    again: it gets the first answer."""
    if idempotency_key is None:
        return await _apply_view(parsed, services, sessions)
    async with services.exclusive(f"idempotency:{client}/{idempotency_key}"):
        kept = await services.io(sessions.store.recall, idempotency_key)
        if kept is not None and kept.digest != parsed.digest:
            raise InputError(("header", "idempotency-key"), (
                f"the Idempotency-Key {idempotency_key!r} was sent before with another body; "
                "a retry sends the same bytes, a new view a new key"))
        if kept is not None:
            return ViewOut.model_validate_json(kept.answer)
        out = await _apply_view(parsed, services, sessions)
        kept = KeptAnswer(out.model_dump_json(), parsed.digest, out.session_id)
        await services.io(sessions.store.remember, idempotency_key, kept)
        return out


async def _apply_view(parsed: ParsedView, services, sessions: Pipeline) -> ViewOut:
    view, session_id = parsed.view, parsed.session_id
    if session_id is None:
        session_id, result = await services.infer(sessions.add_view, None, view)
    else:  # the session's lock is awaited here, outside the inference slots; 503 if it stays
        async with services.exclusive(session_id):
            session_id, result = await services.infer(sessions.add_view, session_id, view)
    return ViewOut(
        session_id=session_id,
        view_index=result.view_index,
        observed_voxels=result.observed_voxels,
        occupied_voxels=result.occupied_voxels,
        completion="registered" if result.registered else "memory",
    )
