"""The HTTP service: every route through FastAPI's TestClient, the limits, the grasp cache.

A tiny untrained MVP stands in for the shipped weights (tests/service_helpers.py). Bad input and
error answers are in tests/test_service_errors.py, the real ``python -m service`` (SIGKILL and
restart, eight concurrent clients, the load generator) in tests/test_service_server.py, the
golden grasp of the shipped MVP in tests/test_service_golden.py; schemathesis runs in
tests/test_front_door.py.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from fastapi.testclient import TestClient
from service_helpers import (
    check_grasp,
    hidden_view,
    new_session,
    occupancy,
    points_view,
    reference,
    save_tiny,
    settings,
    stored_state,
)

from completion.depth import DEPTH_FILTER
from completion.grid import VoxelGrid, pitch_of, transform_points
from completion.mesh import load_mesh_bytes
from grasp_client.wire import depth_f32_m, grid_field, intrinsics_field
from service.app import create_app
from service.load import scene_views

# --------------------------------------------------------------------------------- routes


def test_healthz_and_docs(client):
    r = client.get("/healthz")
    assert r.status_code == 200
    assert r.json()["status"] == "ok" and r.json()["sessions"] == 0
    assert r.json()["model"].endswith("tiny.pt")
    assert client.get("/docs").status_code == 200
    schema = client.get("/openapi.json").json()
    assert {"/views", "/grasp", "/sessions/{session_id}", "/sessions/{session_id}/mesh"} <= set(
        schema["paths"]
    )


def test_points_views_make_a_session(client, tiny_model):
    bodies = [points_view(seed=i) for i in range(3)]
    first = client.post("/views", json=bodies[0]).json()
    sid = first["session_id"]
    answers = [first] + [
        client.post("/views", json=b | {"session_id": sid}).json() for b in bodies[1:]
    ]
    assert [a["view_index"] for a in answers] == [0, 1, 2]
    assert {a["session_id"] for a in answers} == {sid}
    ref = reference(tiny_model, bodies)
    assert answers[-1]["occupied_voxels"] == int(ref.completion().occupancy.sum())
    last = VoxelGrid.from_points(np.asarray(bodies[-1]["points"]))
    assert answers[-1]["observed_voxels"] == int(last.occupancy.sum())

    info = client.get(f"/sessions/{sid}").json()
    assert info["session_id"] == sid and info["views"] == 3 and info["object_seen"] is True
    assert info["created"] <= info["updated"] < info["expires"]
    assert client.get("/healthz").json()["sessions"] == 1


def test_depth_png_mask_and_pose_equal_the_stream(client, tiny_model, scene):
    bodies = scene_views(scene)[:3]
    sid = new_session(client, bodies[0])
    for body in bodies[1:]:
        assert client.post("/views", json=body | {"session_id": sid}).status_code == 200
    ref = reference(tiny_model, bodies)
    occ, answer = occupancy(client, sid)
    np.testing.assert_array_equal(occ, ref.completion().occupancy)
    np.testing.assert_allclose(answer["grid_to_camera"], ref.completion().grid_to_camera)
    assert answer["views"] == 3 and answer["threshold"] == ref.threshold
    assert stored_state(client.app.state.settings.store_path, sid) == ref.to_bytes()


def test_depth_png_voxelizes_like_the_simulator(client, scene):
    """A 16-bit mm PNG + mask gives (to mm rounding) the simulator's own input grid."""
    r = client.post("/views", json=scene_views(scene)[0]).json()
    expected = int(scene.inputs[0].sum())
    assert abs(r["observed_voxels"] - expected) <= max(2, expected // 50)


def test_f32_depth_with_nan_and_inf_as_missing(client, tiny_model, scene):
    """float32 metres (ROS 32FC1): NaN and ±inf mark pixels without a return (REP 117)."""
    depth = scene.depth[0].copy()
    background = scene.mask[0] < 0
    with_zero = {"depth": depth_f32_m(np.where(background, 0.0, depth))}
    marked = np.where(background, np.nan, depth)
    marked[0, 0], marked[0, 1] = np.inf, -np.inf
    with_nan = {"depth": depth_f32_m(marked)}
    k = {"intrinsics": intrinsics_field(scene.meta["intrinsics"])}
    a = client.post("/views", json=with_zero | k).json()
    b = client.post("/views", json=with_nan | k).json()
    assert a["observed_voxels"] == b["observed_voxels"] == int(scene.inputs[0].sum())
    ref = reference(tiny_model, [with_nan | k])
    np.testing.assert_array_equal(occupancy(client, b["session_id"])[0], ref.completion().occupancy)


def test_grid_view(client, tiny_model, scene):
    grid = VoxelGrid(scene.inputs[0], scene.grid_to_camera[0])
    body = {"grid": grid_field(grid)}
    r = client.post("/views", json=body).json()
    assert r["observed_voxels"] == int(scene.inputs[0].sum())
    occ, answer = occupancy(client, r["session_id"])
    np.testing.assert_array_equal(occ, reference(tiny_model, [body]).completion().occupancy)
    np.testing.assert_allclose(answer["grid_to_camera"], scene.grid_to_camera[0])


@pytest.mark.parametrize("fmt", ["ply", "obj", "stl", "glb"])
def test_mesh_downloads(client, fmt):
    body = points_view()
    sid = new_session(client, body)
    r = client.get(f"/sessions/{sid}/mesh", params={"format": fmt})
    assert r.status_code == 200, r.text
    assert r.headers["content-disposition"] == f'attachment; filename="{sid}.{fmt}"'
    mesh = load_mesh_bytes(r.content, fmt)
    assert len(mesh.faces) > 0
    # The mesh is in the camera frame, around the object (the tiny model fills the whole grid).
    _, answer = occupancy(client, sid)
    t = np.asarray(answer["grid_to_camera"])
    lo, hi = t[:3, 3] - t[0, 0], t[:3, 3] + 40 * t[0, 0]
    assert np.all(mesh.bounds[0] >= lo - 1e-6) and np.all(mesh.bounds[1] <= hi + 1e-6)
    points = np.asarray(body["points"])
    points = points[DEPTH_FILTER.inliers(points)]  # the points that frame the grid
    assert np.all(mesh.bounds[0] <= points.min(0)) and np.all(mesh.bounds[1] >= points.max(0))


def test_grasp(client, scene):
    # MVP alone (the route, not the fusion, is under test: its ranked grasps here sort by ε)
    bodies = [body | {"registered": False} for body in scene_views(scene)[:2]]
    sid = new_session(client, bodies[0])
    client.post("/views", json=bodies[1] | {"session_id": sid})
    r = client.get("/grasp", params={"session_id": sid, "top_k": 2, "n_candidates": 8})
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["session_id"] == sid and out["views"] == 2
    timing = out["timing_ms"]
    assert set(timing) == {"load", "completion", "mesh", "planning", "waiting", "total"}
    assert timing["total"] >= timing["planning"] > 0 and timing["waiting"] >= 0
    assert 1 <= len(out["grasps"]) <= 2, out["reason"]
    camera = np.asarray(bodies[1]["camera_pose"])
    for g in out["grasps"]:
        check_grasp(g)
        np.testing.assert_allclose(g["palm_pose_world"], camera @ np.asarray(g["palm_pose"]))
    epsilons = [g["epsilon"] for g in out["grasps"]]
    assert epsilons == sorted(epsilons, reverse=True)


def test_grasp_on_a_support_plane(client, scene):
    """The table under the object (world z of its lowest point): no grasp from below it, no
    hand link below it, in the world frame the plane was given in."""
    from grasp.hand.result import GraspResult, HandDofs, HandJoints
    from grasp.hand.table import hand_points
    from grasp_client.wire import SupportPlane

    bodies = scene_views(scene)[:2]
    sid = new_session(client, bodies[0])
    client.post("/views", json=bodies[1] | {"session_id": sid})
    _, occ = occupancy(client, sid)
    camera = np.asarray(bodies[1]["camera_pose"])
    corners = np.array([[i, j, k, 1.0] for i in (0, 40) for j in (0, 40) for k in (0, 40)])
    lowest = float((camera @ np.asarray(occ["grid_to_camera"]) @ corners.T)[2].min())
    plane = SupportPlane(np.array([0.0, 0.0, 1.0]), -lowest)
    r = client.get("/grasp", params={"session_id": sid, "top_k": 3, "n_candidates": 16,
                                     "support_plane": f"0,0,1,{-lowest}"})
    assert r.status_code == 200, r.text
    assert r.json()["grasps"], r.json()["reason"]
    for g in r.json()["grasps"]:
        world = np.asarray(g["palm_pose_world"])
        assert world[:3, 2] @ plane.normal <= 1e-6  # approach along or down the plane
        # the hand where it closed (a table pinch's palm rose from palm_pose while closing)
        hand = GraspResult(True, "", np.asarray(g["end_palm_pose_world"]),
                           HandJoints(**g["joints_deg"]), HandDofs(*g["dofs_deg"]))
        assert plane.height(hand_points(hand)).min() >= -1e-6
    # the session keeps the plane: reported, and the completion is cut at it
    kept = client.get(f"/sessions/{sid}").json()["support_plane"]
    np.testing.assert_allclose(kept, [0, 0, 1, -lowest], atol=1e-9)
    bits, occ = occupancy(client, sid)
    centres = VoxelGrid(bits, np.asarray(occ["grid_to_camera"])).points()
    assert plane.height(transform_points(centres, camera)).min() >= 0
    again = client.get("/grasp", params={"session_id": sid, "n_candidates": 16}).json()
    assert again["support_plane"] == r.json()["support_plane"]  # without the query: kept


def test_a_support_plane_given_with_a_view_cuts_the_completion_below_it(client, scene):
    bodies = scene_views(scene)[:2]
    camera = np.asarray(bodies[0]["camera_pose"])
    sid = new_session(client, bodies[0])
    bits, occ = occupancy(client, sid)
    z = transform_points(VoxelGrid(bits, np.asarray(occ["grid_to_camera"])).points(), camera)[:, 2]
    middle = float(np.median(z))  # a plane through the middle of the completion
    assert client.get(f"/sessions/{sid}").json()["support_plane"] is None
    r = client.post("/views", json=bodies[1] | {"session_id": sid,
                                                "support_plane": [0, 0, 2, -2 * middle]})
    assert r.status_code == 200, r.text
    assert client.get(f"/sessions/{sid}").json()["support_plane"] == [0, 0, 1, -middle]
    bits, occ = occupancy(client, sid)
    assert occ["occupied_voxels"] == r.json()["occupied_voxels"] > 0
    transform = np.asarray(occ["grid_to_camera"])
    camera = np.asarray(bodies[1]["camera_pose"])
    assert transform_points(VoxelGrid(bits, transform).points(), camera)[:, 2].min() >= middle
    mesh = load_mesh_bytes(client.get(f"/sessions/{sid}/mesh").content, "ply")
    lowest = transform_points(mesh.vertices, camera)[:, 2].min()
    assert lowest >= middle - pitch_of(transform)  # marching cubes closes the cut in a voxel
    no_pose = {k: v for k, v in bodies[1].items() if k != "camera_pose"}
    r = client.post("/views", json=no_pose | {"session_id": sid})
    assert r.status_code == 422 and "camera pose" in r.text, r.text  # the plane needs poses
    r = client.post("/views", json=no_pose | {"support_plane": [0, 0, 1, 0]})
    assert r.status_code == 422 and "camera_pose" in r.text, r.text


def test_a_shape_metres_across_is_answered_without_planning(client):
    """Points spread over metres (valid input: within what a depth camera sees) complete to a
    shape no hand can close on: the answer says so at once instead of approaching it in 10 mm
    steps for minutes."""
    far = {"points": [[-3.0, -3.0, 1.0], [3.0, 3.0, 9.0], [0.0, 0.0, 5.0]]}
    sid = new_session(client, far)
    t0 = time.perf_counter()
    r = client.get("/grasp", params={"session_id": sid, "n_candidates": 16})
    assert r.status_code == 200 and r.json()["grasps"] == []
    assert "the planner tries shapes up to 2 m" in r.json()["reason"]
    assert time.perf_counter() - t0 < 30


@pytest.mark.parametrize("value", ["0,0,1", "up", "0,0,0,1"])
def test_bad_support_plane_is_422(client, value):
    sid = new_session(client)
    r = client.get("/grasp", params={"session_id": sid, "support_plane": value})
    assert r.status_code == 422 and "support_plane" in r.text


def test_support_plane_needs_camera_poses(client):
    sid = new_session(client)  # points without a camera_pose
    r = client.get("/grasp", params={"session_id": sid, "support_plane": "0,0,1,0"})
    assert r.status_code == 422 and "camera_pose" in r.text, r.text


def test_grasp_without_camera_pose_has_no_world_pose(client, scene):
    body = scene_views(scene, with_pose=False)[0]
    sid = new_session(client, body)
    out = client.get("/grasp", params={"session_id": sid, "n_candidates": 8}).json()
    assert out["grasps"] and all(g["palm_pose_world"] is None for g in out["grasps"])


def test_delete_session(client):
    sid = new_session(client)
    assert client.delete(f"/sessions/{sid}").status_code == 204
    for method, path in [
        ("GET", f"/sessions/{sid}"),
        ("DELETE", f"/sessions/{sid}"),
        ("GET", f"/sessions/{sid}/mesh"),
        ("GET", f"/sessions/{sid}/occupancy"),
    ]:
        r = client.request(method, path)
        assert r.status_code == 404 and "unknown session" in r.json()["detail"]
    r = client.get("/grasp", params={"session_id": sid})
    assert r.status_code == 404 and f"unknown session {sid!r}" in r.json()["detail"]
    r = client.post("/views", json=points_view() | {"session_id": sid})
    assert r.status_code == 404 and "POST /views without session_id" in r.json()["detail"]


# --------------------------------------------------------------------------------- limits


def test_token(tmp_path, tiny_model):
    with TestClient(create_app(settings(tmp_path, tiny_model, token="s3cret"))) as client:
        assert client.get("/healthz").status_code == 200  # liveness needs no token
        r = client.post("/views", json=points_view())
        assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
        assert "missing bearer token" in r.json()["detail"]
        r = client.post("/views", json=points_view(), headers={"Authorization": "Bearer nope"})
        assert r.status_code == 401 and "wrong bearer token" in r.json()["detail"]
        r = client.get("/sessions/x", headers={"Authorization": "Basic czNjcmV0"})
        assert r.status_code == 401 and "missing bearer token" in r.json()["detail"]
        assert client.get("/healthz").json()["sessions"] == 0
        ok = {"Authorization": "Bearer s3cret"}
        sid = client.post("/views", json=points_view(), headers=ok).json()["session_id"]
        assert client.get(f"/sessions/{sid}", headers=ok).status_code == 200
        assert client.get(f"/sessions/{sid}").status_code == 401


def test_store_full_is_503(tmp_path, tiny_model):
    with TestClient(create_app(settings(tmp_path, tiny_model, max_sessions=2))) as client:
        a, _ = new_session(client), new_session(client)
        r = client.post("/views", json=points_view())
        assert r.status_code == 503 and r.headers["retry-after"] == "60"
        assert r.json()["detail"].startswith("the session store is full (2 sessions)")
        assert client.post("/views", json=points_view() | {"session_id": a}).status_code == 200
        client.delete(f"/sessions/{a}")
        assert client.post("/views", json=points_view()).status_code == 200


def test_idle_sessions_expire(tmp_path, tiny_model):
    with TestClient(
        create_app(settings(tmp_path, tiny_model, session_ttl_s=60, max_sessions=1))
    ) as client:
        store = client.app.state.services.pipeline.store
        now = [1000.0]
        store.clock = lambda: now[0]  # the store's time, moved by hand
        sid = new_session(client)
        now[0] += 40
        assert client.post("/views", json=points_view() | {"session_id": sid}).status_code == 200
        now[0] += 40  # 80 s after creation, 40 s after the last view: alive
        info = client.get(f"/sessions/{sid}").json()
        assert info["views"] == 2 and info["expires"] == "1970-01-01T00:18:20Z"
        assert client.post("/views", json=points_view()).status_code == 503  # full
        now[0] += 21
        r = client.get(f"/sessions/{sid}")
        assert r.status_code == 404 and "expired after 60 s without a view" in r.json()["detail"]
        assert client.get("/healthz").json()["sessions"] == 0
        assert client.post("/views", json=points_view()).status_code == 200  # room again


def test_sessions_that_never_saw_the_object_expire_sooner(tmp_path, tiny_model):
    config = settings(tmp_path, tiny_model, session_ttl_s=600, unseen_session_ttl_s=30,
                      max_sessions=2)
    with TestClient(create_app(config)) as client:
        store = client.app.state.services.pipeline.store
        now = [1000.0]
        store.clock = lambda: now[0]
        empty = client.post("/views", json=hidden_view()).json()["session_id"]
        seen = new_session(client)
        assert client.get(f"/sessions/{empty}").json()["expires"] == "1970-01-01T00:17:10Z"
        assert client.post("/views", json=points_view()).status_code == 503  # full
        now[0] += 31
        r = client.get(f"/sessions/{empty}")
        assert r.status_code == 404 and "30 s while no view had shown the object" in r.text
        assert client.get(f"/sessions/{seen}").status_code == 200  # 600 s for a seen one
        assert client.post("/views", json=points_view()).status_code == 200  # room again


def test_session_of_another_model_is_409(tmp_path, tiny_model):
    with TestClient(create_app(settings(tmp_path, tiny_model))) as client:
        sid = new_session(client)
    other = save_tiny(tmp_path / "other.pt", seed=1)
    with TestClient(create_app(settings(tmp_path, other))) as client:
        r = client.post("/views", json=points_view() | {"session_id": sid})
        assert r.status_code == 409
        assert f"session {sid!r} was made by another model" in r.json()["detail"]
        assert "start a new session" in r.json()["detail"]
        assert client.get(f"/sessions/{sid}").json()["views"] == 1


def test_missing_weights_fail_at_startup_not_import(tmp_path):
    app = create_app(settings(tmp_path, str(tmp_path / "missing.pt")))  # no model loaded yet
    with pytest.raises(FileNotFoundError, match="missing.pt does not exist"):
        with TestClient(app):
            pass


def test_views_are_capped_only_where_the_state_grows(tmp_path):
    """An MVT session (its key/value cache grows with every view) stops at GRASP_MAX_VIEWS with
    409; an MVP session (fixed-size state) is not capped."""
    mvt = save_tiny(tmp_path / "mvt.pt", kind="mvt")
    with TestClient(create_app(settings(tmp_path / "a", mvt, max_views=2))) as client:
        sid = new_session(client)
        assert client.post("/views", json=points_view() | {"session_id": sid}).status_code == 200
        r = client.post("/views", json=points_view() | {"session_id": sid})
        assert r.status_code == 409 and "has 2 views, the most" in r.json()["detail"]
        assert client.get(f"/sessions/{sid}").json()["views"] == 2  # nothing lost
    mvp = save_tiny(tmp_path / "mvp.pt", kind="mvp")
    with TestClient(create_app(settings(tmp_path / "b", mvp, max_views=2))) as client:
        sid = new_session(client)
        for _ in range(3):
            r = client.post("/views", json=points_view() | {"session_id": sid})
            assert r.status_code == 200


def test_token_is_checked_before_the_body_is_read(tmp_path, tiny_model):
    """Without the token, even a body that is not JSON gets 401, not 422: the gate answers
    before the app reads it. The inspector page and its assets need no token."""
    with TestClient(create_app(settings(tmp_path, tiny_model, token="s3cret"))) as client:
        json_type = {"content-type": "application/json"}
        r = client.post("/views", content=b"{not json", headers=json_type)
        assert r.status_code == 401 and "missing bearer token" in r.json()["detail"]
        ok = {"Authorization": "Bearer s3cret"}
        r = client.post("/views", content=b"{not json", headers=ok | json_type)
        assert r.status_code == 422
        sid = client.post("/views", json=points_view(), headers=ok).json()["session_id"]
        page = client.get(f"/sessions/{sid}/view")
        other = client.get("/sessions/abc/view")  # public: it never says whether a session is
        assert page.status_code == other.status_code == 200 and page.content == other.content
        assert client.get("/static/inspector/inspector.js").status_code == 200
        assert client.get("/sessions/abc/observed").status_code == 401
        assert client.get("/openapi.json").status_code == 200


# --------------------------------------------------------------------------------- planner


def test_repeated_grasp_on_an_unchanged_session_is_cached(client, scene):
    bodies = scene_views(scene)[:2]
    sid = new_session(client, bodies[0])
    params = {"session_id": sid, "top_k": 2, "n_candidates": 8}
    first = client.get("/grasp", params=params).json()
    again = client.get("/grasp", params=params).json()
    assert first["cached"] is False and again["cached"] is True
    assert again["grasps"] == first["grasps"] and again["timing_ms"]["planning"] == 0.0
    assert client.get("/grasp", params=params | {"top_k": 1}).json()["cached"] is False
    client.post("/views", json=bodies[1] | {"session_id": sid})  # a new view: a new mesh
    assert client.get("/grasp", params=params).json()["cached"] is False


def test_planner_queue_is_bounded_and_gone_clients_are_dropped(monkeypatch):
    """One worker, no queue: a second plan while the first runs is refused (503 upstream);
    a plan whose client left while it waited never reaches the worker."""
    import asyncio
    import time as _time

    from service.engine import planning

    calls = []

    def slow_plan(request):
        calls.append(request)
        _time.sleep(0.3)
        return [], 0.3

    monkeypatch.setattr(planning, "plan_grasps", slow_plan)
    mesh = (np.zeros((3, 3)), np.array([[0, 1, 2]]))

    def asked(n):
        return planning.PlanRequest(*mesh, n_candidates=n, seed=0, top_k=1)

    async def scenario():
        planner = planning.Planner(1, processes=False, queue=0, cache=0)
        first = asyncio.create_task(planner.plan(asked(4)))
        await asyncio.sleep(0.05)
        with pytest.raises(planning.PlannerBusy, match="try again"):
            await planner.plan(asked(5))
        await first
        queued = planning.Planner(1, processes=False, queue=1, cache=0)
        running = asyncio.create_task(queued.plan(asked(6)))
        await asyncio.sleep(0.05)

        async def gone():
            return True

        with pytest.raises(planning.ClientGone):
            await queued.plan(asked(7), gone=gone)
        await running
        assert queued.pending == 0

    asyncio.run(scenario())
    assert [c.n_candidates for c in calls] == [4, 6]


def test_min_hold_reaches_the_planner_and_is_checked(client, scene, monkeypatch):
    """``GET /grasp?min_hold=``: outside [0, 1] a 422 on the field; inside, the planner gets it
    (a plan of its own: not another min_hold's cached one)."""
    from service.engine import planning

    asked = []
    real = planning.plan_grasps
    monkeypatch.setattr(planning, "plan_grasps", lambda r: asked.append(r.min_hold) or real(r))
    sid = new_session(client, scene_views(scene)[0])
    r = client.get("/grasp", params={"session_id": sid, "min_hold": 1.5})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "min_hold"]
    for value in (0.5, 0.3):
        r = client.get("/grasp", params={"session_id": sid, "n_candidates": 8, "min_hold": value})
        assert r.status_code == 200 and r.json()["cached"] is False, r.text
    assert asked == [0.5, 0.3]
