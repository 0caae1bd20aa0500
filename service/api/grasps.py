"""``GET /grasp``: complete the session's current state, mesh it and plan BarrettHand grasps on it
(:func:`plan_session`, which the inspector's ``scene.glb`` shares)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Annotated

import trimesh
from fastapi import APIRouter, Depends, Query, Request

from grasp.planner import too_large, wire_grasp
from grasp_client.wire import SupportPlane
from service.api.depends import (
    ClientDep,
    PlanQuery,
    ServicesDep,
    SessionsDep,
    require_token,
    responses,
)
from service.api.schemas import GraspsOut
from service.engine.pipeline import Pipeline, Snapshot
from service.engine.planning import PlanRequest
from service.intake.inputs import InputError
from service.services import Services

router = APIRouter(dependencies=[Depends(require_token)], responses=responses(401, 413, 422))


@router.get("/grasp", response_model=GraspsOut, responses=responses(404, 409, 503))
async def get_grasp(
    services: ServicesDep,
    sessions: SessionsDep,
    client: ClientDep,
    request: Request,
    session_id: Annotated[str, Query(min_length=1, max_length=128)],
    query: Annotated[PlanQuery, Depends()],
) -> GraspsOut:
    """Complete the session's current state, mesh it and plan BarrettHand grasps."""
    return (await plan_session(services, sessions, client, request, session_id, query)).answer


@dataclass(frozen=True)
class Planned:
    """What :func:`plan_session` answers, the completion mesh it planned on (camera frame) and
    the snapshot both came from."""

    answer: GraspsOut
    mesh: trimesh.Trimesh
    snapshot: Snapshot


async def plan_session(
    services: Services, sessions: Pipeline, client: str, request: Request, session_id: str,
    query: PlanQuery,
) -> Planned:
    """Plan on the session (one of ``sessions``, the client's) as ``query`` asks: the session is
    read once (a query's support plane is stored with it under its lock, as a view's), the mesh
    goes to a planner worker once, in the ``client``'s turn."""
    start = time.perf_counter()
    s = services.settings
    n = s.n_candidates if query.n_candidates is None else query.n_candidates
    if n > s.max_candidates:
        raise InputError(
            ("query", "n_candidates"), f"n_candidates must be at most {s.max_candidates}, got {n}"
        )
    tries = s.verify if query.verify is None else query.verify
    if tries > s.max_verify:
        raise InputError(("query", "verify"), f"verify must be at most {s.max_verify} grasps "
                         f"(GRASP_MAX_VERIFY), got {tries}")
    if query.support_plane is None:
        snapshot, mesh, timing = await services.infer(sessions.grasp_mesh, session_id)
    else:
        try:
            given = SupportPlane.parse(query.support_plane)
        except ValueError as exc:
            raise InputError(("query", "support_plane"), str(exc)) from None
        async with services.exclusive(session_id):  # the session keeps it from now on
            snapshot, mesh, timing = await services.infer(
                sessions.grasp_mesh, session_id, given)
    plane = None
    if snapshot.support_plane is not None:  # into the latest camera frame
        plane = snapshot.support_plane.transformed(snapshot.camera_to_world)
    problem = too_large(mesh)
    if problem is not None:  # nothing the hand can close on: say so, plan nothing
        timing |= {"planning": 0.0, "waiting": 0.0, "total": (time.perf_counter() - start) * 1e3}
        out = _grasps_out(snapshot, [], timing, plane)
        out.reason = problem
        return Planned(out, mesh, snapshot)
    asked = PlanRequest(mesh.vertices, mesh.faces, n_candidates=n, seed=s.plan_seed,
                        top_k=query.top_k, budget=s.plan_budget, support_plane=plane,
                        obstacles=snapshot.obstacles, verify=tries, min_hold=query.min_hold)
    results, seconds, cached = await services.planner.plan(asked, client=client,
                                                          gone=request.is_disconnected)
    await services.io(sessions.store.get, session_id)  # deleted while it was planned: 404
    total = (time.perf_counter() - start) * 1e3
    timing["planning"] = 0.0 if cached else seconds * 1e3
    timing |= {"waiting": max(total - sum(timing.values()), 0.0), "total": total}
    out = _grasps_out(snapshot, results, timing, plane)
    out.cached = cached
    return Planned(out, mesh, snapshot)


def _grasps_out(
    snapshot: Snapshot, results: list, timing_ms: dict[str, float], plane: SupportPlane | None
) -> GraspsOut:
    held = [r for r in results if r.success]
    reasons = sorted({r.reason for r in results if not r.success and r.reason})
    camera = snapshot.camera_to_world
    return GraspsOut(
        session_id=snapshot.record.id,
        views=snapshot.record.views,
        grasps=[wire_grasp(r, camera) for r in held],
        reason=None if held else ("; ".join(reasons) or "no grasp candidate"),
        camera_pose=camera,
        support_plane=plane,
        obstacle_voxels=0 if snapshot.obstacles is None else len(snapshot.obstacles),
        timing_ms={k: round(v, 3) for k, v in timing_ms.items()},
    )
