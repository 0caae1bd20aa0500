"""A session's resources: its summary (``GET``/``DELETE /sessions/{id}``), its completion as a
mesh and as a grid, and the service's liveness (``/healthz``)."""

from __future__ import annotations

import base64
from datetime import UTC, datetime
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Response, status

from completion.mesh import MeshFormat, export_mesh
from completion.stream import stored_registration, stored_support_plane
from service.api.depends import PathId, ServicesDep, SessionsDep, require_token, responses
from service.api.schemas import HealthOut, OccupancyOut, SessionOut
from service.store.base import SessionNotFound

MEDIA_TYPES = {
    "ply": "application/octet-stream",
    "obj": "text/plain",
    "stl": "model/stl",
    "glb": "model/gltf-binary",
}

router = APIRouter(dependencies=[Depends(require_token)], responses=responses(401, 413, 422))
health_router = APIRouter()


@router.get("/sessions/{session_id}", response_model=SessionOut, responses=responses(404))
async def get_session(
    session_id: PathId, services: ServicesDep, sessions: SessionsDep
) -> SessionOut:
    """A session's view count, times and the support plane it keeps."""
    record = await services.io(sessions.store.get, session_id)
    ttl = sessions.store.ttl_of(record)
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
    "/sessions/{session_id}", status_code=status.HTTP_204_NO_CONTENT, responses=responses(404)
)
async def delete_session(
    session_id: PathId, services: ServicesDep, sessions: SessionsDep
) -> Response:
    """Forget a session (and the idempotent answers of its views)."""
    store = sessions.store
    if not await services.io(store.delete, session_id):
        raise SessionNotFound(store.not_found_message(session_id))
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get(
    "/sessions/{session_id}/mesh",
    response_class=Response,
    responses={
        200: {"content": {m: {} for m in MEDIA_TYPES.values()}, "description": "mesh file"},
        **responses(404, 409),
    },
)
async def get_mesh(
    session_id: PathId,
    services: ServicesDep,
    sessions: SessionsDep,
    mesh_format: Annotated[MeshFormat, Query(alias="format")] = "ply",
) -> Response:
    """The completed shape as a mesh in metres, in the latest view's camera frame."""
    mesh = await services.infer(sessions.mesh, session_id)
    data = await services.infer(export_mesh, mesh, mesh_format)
    return Response(
        data,
        media_type=MEDIA_TYPES[mesh_format],
        headers={"Content-Disposition": f'attachment; filename="{session_id}.{mesh_format}"'},
    )


@router.get(
    "/sessions/{session_id}/occupancy", response_model=OccupancyOut, responses=responses(404, 409)
)
async def get_occupancy(
    session_id: PathId, services: ServicesDep, sessions: SessionsDep
) -> OccupancyOut:
    """The completion thresholded to a 40³ grid (packed bits) with its ``grid_to_camera``."""
    snapshot, grid = await services.infer(sessions.occupancy, session_id)
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
