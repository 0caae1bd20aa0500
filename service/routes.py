"""HTTP routes: ``POST /views``, ``GET /grasp``, ``/sessions/{id}`` (mesh, occupancy), ``/healthz``.

Each route checks its input, hands the blocking work to a worker thread and shapes the answer;
errors are raised as exceptions that :mod:`service.app` turns into 4xx answers.
"""

from __future__ import annotations

import base64
import math
import time
from collections.abc import AsyncIterator
from datetime import UTC, datetime
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Depends, Header, Path, Query, Request, Response, status

from completion.mesh import MeshFormat, export_mesh
from completion.stream import stored_registration, stored_support_plane
from grasp.hand.autograsp import pregrasp_pose
from grasp.hand.table import hand_primitives
from grasp.planner import palm_touches, too_large
from grasp_client.wire import JOINT_NAMES, Contact, Grasp, Primitive, SupportPlane
from service.deps import Services, ServicesDep, require_token
from service.inputs import InputError
from service.parsing import ParsedView
from service.pipeline import Snapshot
from service.planning import PlanRequest
from service.schemas import (
    ErrorOut,
    GraspsOut,
    HealthOut,
    OccupancyOut,
    SessionOut,
    ViewOut,
)
from service.store import SessionNotFound

MEDIA_TYPES = {
    "ply": "application/octet-stream",
    "obj": "text/plain",
    "stl": "model/stl",
    "glb": "model/gltf-binary",
}
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


def _errors(*codes: int) -> dict:
    return {code: {"model": ErrorOut, "description": _WHY[code]} for code in codes}


router = APIRouter(dependencies=[Depends(require_token)], responses=_errors(401, 413, 422))
health_router = APIRouter()
PathId = Annotated[str, Path(min_length=1, max_length=128, description="from POST /views")]


async def view_body(request: Request, services: ServicesDep) -> AsyncIterator[ParsedView]:
    """The body, read under the size limit, then parsed, validated and decoded off the event
    loop (:mod:`service.parsing`), its memory reserved until the answer is out
    (:mod:`service.memory`)."""
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
    responses=_errors(400, 404, 409, 503),
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


@router.get("/grasp", response_model=GraspsOut, responses=_errors(404, 409, 503))
async def get_grasp(
    services: ServicesDep,
    request: Request,
    session_id: Annotated[str, Query(min_length=1, max_length=128)],
    top_k: TopK = 1,
    n_candidates: NCandidates = None,
    support_plane: SupportPlaneQuery = None,
    verify: VerifyQuery = None,
) -> GraspsOut:
    """Complete the session's current state, mesh it and plan BarrettHand grasps."""
    out, _, _ = await plan_session(
        services, request, session_id, top_k, n_candidates, support_plane, verify
    )
    return out


async def plan_session(
    services: Services,
    request: Request,
    session_id: str,
    top_k: int,
    n_candidates: int | None,
    support_plane: str | None,
    verify: int | None = None,
):
    """What ``GET /grasp`` answers, the completion mesh it planned on (camera frame) and the
    snapshot both came from."""
    start = time.perf_counter()
    s = services.settings
    n = s.n_candidates if n_candidates is None else n_candidates
    if n > s.max_candidates:
        raise InputError(
            ("query", "n_candidates"), f"n_candidates must be at most {s.max_candidates}, got {n}"
        )
    tries = s.verify if verify is None else verify
    if tries > s.max_verify:
        raise InputError(("query", "verify"), f"verify must be at most {s.max_verify} grasps "
                         f"(GRASP_MAX_VERIFY), got {tries}")
    plane = None
    if support_plane is not None:
        try:
            plane = SupportPlane.parse(support_plane)
        except ValueError as exc:
            raise InputError(("query", "support_plane"), str(exc)) from None
        async with services.exclusive(session_id):  # the session keeps it from now on
            await services.infer(services.pipeline.set_support_plane, session_id, plane)
    snapshot, mesh, timing = await services.infer(services.pipeline.grasp_mesh, session_id)
    plane = None
    if snapshot.support_plane is not None:  # into the latest camera frame
        plane = snapshot.support_plane.transformed(snapshot.camera_to_world)
    problem = too_large(mesh)
    if problem is not None:  # nothing the hand can close on: say so, plan nothing
        timing |= {"planning": 0.0, "waiting": 0.0, "total": (time.perf_counter() - start) * 1e3}
        out = _grasps_out(snapshot, [], timing, plane)
        out.reason = problem
        return out, mesh, snapshot
    asked = PlanRequest(mesh.vertices, mesh.faces, n_candidates=n, seed=s.plan_seed,
                        top_k=top_k, budget=s.plan_budget, support_plane=plane,
                        obstacles=snapshot.obstacles, verify=tries)
    results, seconds, cached = await services.planner.plan(asked, gone=request.is_disconnected)
    await services.io(services.pipeline.store.get, session_id)  # deleted while it was planned: 404
    total = (time.perf_counter() - start) * 1e3
    timing["planning"] = 0.0 if cached else seconds * 1e3
    timing |= {"waiting": max(total - sum(timing.values()), 0.0), "total": total}
    out = _grasps_out(snapshot, results, timing, plane)
    out.cached = cached
    return out, mesh, snapshot


@router.get("/sessions/{session_id}", response_model=SessionOut, responses=_errors(404))
async def get_session(session_id: PathId, services: ServicesDep) -> SessionOut:
    """A session's view count, times and the support plane it keeps."""
    record = await services.io(services.pipeline.store.get, session_id)
    ttl = services.pipeline.store.ttl_of(record)
    plane = await services.io(stored_support_plane, record.state)
    registered, fused = await services.io(stored_registration, record.state)
    return SessionOut(
        session_id=record.id,
        views=record.views,
        object_seen=record.object_seen,
        created=datetime.fromtimestamp(record.created, UTC),
        updated=datetime.fromtimestamp(record.updated, UTC),
        expires=datetime.fromtimestamp(record.updated + ttl, UTC),
        support_plane=plane,
        registered=registered,
        completion="registered" if fused else "memory",
    )


@router.delete(
    "/sessions/{session_id}", status_code=status.HTTP_204_NO_CONTENT, responses=_errors(404)
)
async def delete_session(session_id: PathId, services: ServicesDep) -> Response:
    """Forget a session."""
    store = services.pipeline.store
    if not await services.io(store.delete, session_id):
        raise SessionNotFound(store.not_found_message(session_id))
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get(
    "/sessions/{session_id}/mesh",
    response_class=Response,
    responses={
        200: {"content": {m: {} for m in MEDIA_TYPES.values()}, "description": "mesh file"},
        **_errors(404, 409),
    },
)
async def get_mesh(
    session_id: PathId,
    services: ServicesDep,
    mesh_format: Annotated[MeshFormat, Query(alias="format")] = "ply",
) -> Response:
    """The completed shape as a mesh in metres, in the latest view's camera frame."""
    mesh = await services.infer(services.pipeline.mesh, session_id)
    data = await services.infer(export_mesh, mesh, mesh_format)
    return Response(
        data,
        media_type=MEDIA_TYPES[mesh_format],
        headers={"Content-Disposition": f'attachment; filename="{session_id}.{mesh_format}"'},
    )


@router.get(
    "/sessions/{session_id}/occupancy", response_model=OccupancyOut, responses=_errors(404, 409)
)
async def get_occupancy(session_id: PathId, services: ServicesDep) -> OccupancyOut:
    """The completion thresholded to a 40³ grid (packed bits) with its ``grid_to_camera``."""
    snapshot, grid = await services.infer(services.pipeline.occupancy, session_id)
    return OccupancyOut(
        session_id=session_id,
        views=snapshot.record.views,
        shape=list(grid.occupancy.shape),
        data=base64.b64encode(grid.pack()).decode(),
        threshold=snapshot.completion.threshold,
        occupied_voxels=int(grid.occupancy.sum()),
        grid_to_camera=grid.grid_to_camera.tolist(),
    )


@health_router.get("/healthz", response_model=HealthOut)
async def healthz(services: ServicesDep) -> HealthOut:
    """Liveness: the model is loaded and the store answers (no token needed)."""
    sessions = await services.io(services.pipeline.store.count)
    return HealthOut(model=services.pipeline.model_name, sessions=sessions)


def _grasps_out(
    snapshot: Snapshot, results: list, timing_ms: dict[str, float], plane: SupportPlane | None
) -> GraspsOut:
    held = [r for r in results if r.success]
    reasons = sorted({r.reason for r in results if not r.success and r.reason})
    camera = snapshot.camera_to_world
    return GraspsOut(
        session_id=snapshot.record.id,
        views=snapshot.record.views,
        grasps=[_grasp_out(r, camera) for r in held],
        reason=None if held else ("; ".join(reasons) or "no grasp candidate"),
        camera_pose=camera,
        support_plane=plane,
        obstacle_voxels=0 if snapshot.obstacles is None else len(snapshot.obstacles),
        timing_ms={k: round(v, 3) for k, v in timing_ms.items()},
    )


def _grasp_out(result, camera_to_world: np.ndarray | None) -> Grasp:
    palm = np.asarray(result.palm_pose, dtype=np.float64)
    before = pregrasp_pose(palm)
    end = np.asarray(result.end_palm_pose, dtype=np.float64)
    world = None if camera_to_world is None else np.asarray(camera_to_world, dtype=np.float64)
    return Grasp(
        palm_pose=palm,
        palm_pose_world=None if world is None else world @ palm,
        pregrasp_pose=before,
        pregrasp_pose_world=None if world is None else world @ before,
        joints_deg=dict(zip(JOINT_NAMES, map(float, result.joints_deg), strict=True)),
        dofs_deg=np.asarray(result.dofs_deg, dtype=np.float64),
        epsilon=float(result.epsilon),
        volume=float(result.volume),
        force_epsilon=float(result.force_epsilon),
        palm_contact=palm_touches(result),
        approach_stop=result.approach_stop,
        hold_probability=None if math.isnan(result.hold_probability)
        else float(result.hold_probability),
        verification=result.verification,
        contacts=[Contact(c.link, np.asarray(c.point, dtype=np.float64),
                          np.asarray(c.normal, dtype=np.float64)) for c in result.contacts],
        hand=[Primitive(link, kind, [float(v) for v in size], pose)
              for link, kind, size, pose in hand_primitives(result)],
        kind=result.kind,
        wrist_rise=result.wrist_rise,
        preshape_deg=float(result.preshape_deg),
        end_palm_pose=end,
        end_palm_pose_world=None if world is None else world @ end,
    )
