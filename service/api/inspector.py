"""The grasp inspector: a 3-D page served by the service, and the same scene as one GLB file.

``GET /sessions/{id}/view`` serves a static page (``service/static/inspector/``; three.js is
vendored there with its licence, so it works with no internet). The page holds no data: it reads
``GET /grasp``, ``GET /sessions/{id}/mesh?format=obj`` and ``GET /sessions/{id}/observed``, the
API every client uses, and draws the latest view's observed points, the completion
(semi-transparent), the BarrettHand at each of the top-k grasps (its links placed by the hand's
kinematics, :func:`grasp.hand.table.hand_primitives`) and the support plane when one was given.
The page and its assets need no token (they carry no data); its API calls send the token given
in the page's URL fragment (``#token=…``), which browsers never send to the server.

``GET /sessions/{id}/scene.glb`` writes that scene for Blender or MeshLab: nodes ``completion``,
``observed`` (points), ``grasp_1`` … ``grasp_k`` (one hand each) and ``support_plane``.
"""

from __future__ import annotations

from pathlib import Path as FilePath
from typing import Annotated

import numpy as np
import trimesh
from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import FileResponse

from grasp_client.wire import SupportPlane, b64
from service.api.depends import (
    ClientDep,
    PathId,
    SceneQuery,
    ServicesDep,
    SessionsDep,
    require_token,
    responses,
)
from service.api.grasps import plan_session
from service.api.schemas import GraspsOut, ObservedFormat, ObservedOut

STATIC = FilePath(__file__).resolve().parents[1] / "static" / "inspector"
#: Side of the square drawn for the support plane, in units of the completion's size.
PLANE_SCALE = 3.0

#: The page (public: a browser cannot send the token with a link); its assets are STATIC.
page_router = APIRouter()
#: What the page fetches, with the token as every data route.
data_router = APIRouter(dependencies=[Depends(require_token)], responses=responses(401, 413, 422))


@page_router.get(
    "/sessions/{session_id}/view",
    response_class=FileResponse,
    responses={200: {"content": {"text/html": {}}, "description": "the inspector page"}},
)
async def view_page(session_id: PathId) -> FileResponse:
    """The inspector page of a session (open it in a browser; ?top_k=…&support_plane=…).

    The page is public (a browser cannot send the bearer token with a link) and the same for
    every id, so it never says whether a session exists; what it shows it fetches with the
    token from the fragment (#token=…), and a session that does not exist shows as that 404."""
    return FileResponse(STATIC / "index.html", media_type="text/html")


@data_router.get(
    "/sessions/{session_id}/observed", response_model=ObservedOut, responses=responses(404, 409)
)
async def get_observed(
    session_id: PathId,
    services: ServicesDep,
    sessions: SessionsDep,
    encoding: Annotated[ObservedFormat, Query(alias="format")] = "f32",
) -> ObservedOut:
    """The latest view's observed voxel centres and the session's obstacle voxels, in its
    camera frame (the completion's): as float32 rows in base64 (``format=f32``, the default:
    50,000 obstacles take 0.8 MB), or as JSON lists (``format=json``)."""
    snapshot = await services.infer(sessions.snapshot, session_id)
    obstacles = np.zeros((0, 3)) if snapshot.obstacles is None else snapshot.obstacles
    write = _f32 if encoding == "f32" else (lambda a: np.round(a, 6).tolist())
    return ObservedOut(
        session_id=session_id,
        views=snapshot.record.views,
        format=encoding,
        n_points=len(snapshot.observed),
        n_obstacles=len(obstacles),
        points=write(snapshot.observed),
        obstacles=write(obstacles),
    )


def _f32(points: np.ndarray) -> str:
    return b64(np.ascontiguousarray(points, dtype="<f4").tobytes())


@data_router.get(
    "/sessions/{session_id}/scene.glb",
    response_class=Response,
    responses={
        200: {"content": {"model/gltf-binary": {}}, "description": "the scene as GLB"},
        **responses(404, 409, 503),
    },
)
async def get_scene(
    session_id: PathId,
    services: ServicesDep,
    sessions: SessionsDep,
    client: ClientDep,
    request: Request,
    query: Annotated[SceneQuery, Depends()],
) -> Response:
    """The inspector's scene as one GLB file (latest camera frame, metres)."""
    planned = await plan_session(services, sessions, client, request, session_id, query)
    data = await services.infer(scene_glb, planned.answer, planned.mesh, planned.snapshot.observed)
    return Response(
        data,
        media_type="model/gltf-binary",
        headers={"Content-Disposition": f'attachment; filename="{session_id}.glb"'},
    )


def hand_mesh(grasp) -> trimesh.Trimesh:
    """One grasp's hand (a :class:`grasp_client.wire.Grasp`) as one mesh of its placed
    primitives."""
    parts = []
    for prim in grasp.hand:
        pose = np.asarray(prim.pose, dtype=np.float64)
        if prim.kind == "box":
            parts.append(trimesh.creation.box(extents=prim.size, transform=pose))
        else:
            radius, length = prim.size
            parts.append(trimesh.creation.cylinder(radius, length, sections=24, transform=pose))
    return trimesh.util.concatenate(parts)


def plane_mesh(plane: SupportPlane, centre: np.ndarray, side: float) -> trimesh.Trimesh:
    """A thin square of the plane around the point nearest ``centre``."""
    normal = plane.normal
    point = centre - plane.height(centre) * normal
    pose = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], normal)
    pose[:3, 3] = point
    return trimesh.creation.box(extents=[side, side, 1e-3], transform=pose)


def scene_glb(plan: GraspsOut, mesh: trimesh.Trimesh, points: np.ndarray) -> bytes:
    """The scene of :func:`get_scene` as GLB bytes."""
    scene = trimesh.Scene()
    completion = mesh.copy()
    completion.visual.face_colors = [224, 138, 60, 115]  # semi-transparent orange
    scene.add_geometry(completion, geom_name="completion", node_name="completion")
    if len(points):
        cloud = trimesh.PointCloud(points, colors=np.tile([31, 95, 214, 255], (len(points), 1)))
        scene.add_geometry(cloud, geom_name="observed", node_name="observed")
    for i, grasp in enumerate(plan.grasps, 1):
        hand = hand_mesh(grasp)
        hand.visual.face_colors = [85, 90, 102, 255]
        scene.add_geometry(hand, geom_name=f"grasp_{i}", node_name=f"grasp_{i}")
    if plan.support_plane is not None:
        side = PLANE_SCALE * float(np.linalg.norm(mesh.extents))
        ground = plane_mesh(plan.support_plane, np.asarray(mesh.bounds.mean(axis=0)), side)
        ground.visual.face_colors = [90, 160, 90, 90]
        scene.add_geometry(ground, geom_name="support_plane", node_name="support_plane")
    return scene.export(file_type="glb")
