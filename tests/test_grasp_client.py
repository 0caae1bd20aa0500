"""grasp_client (clients/python): the same grasps as raw HTTP against a real ``python -m
service``, inputs checked before anything is sent, errors as exceptions with the service's
message, retries."""

from __future__ import annotations

import base64

import httpx
import numpy as np
import pytest
from service_helpers import Server, free_port, post_views

from completion.grid import VoxelGrid
from grasp_client import (
    Grasp,
    GraspClient,
    InvalidRequest,
    NothingSeen,
    Unauthorized,
)
from grasp_client import client as grasp_client
from hands.barrett import JOINT_NAMES
from service.load import scene_views


@pytest.fixture(scope="module")
def server(tmp_path_factory, tiny_model):
    tmp = tmp_path_factory.mktemp("client")
    s = Server(tmp, tiny_model, tmp / "store.sqlite", token="secret")
    yield s
    s.stop()


def _mm(depth_m: np.ndarray) -> np.ndarray:
    return np.round(np.nan_to_num(depth_m) * 1000).astype(np.uint16)


@pytest.mark.slow
def test_a_scene_through_the_client_gives_the_grasp_of_the_raw_calls(server, scene):
    headers = {"Authorization": "Bearer secret"}
    sid, _ = post_views(server.url, scene_views(scene), headers=headers)
    raw = httpx.get(f"{server.url}/grasp", params={"session_id": sid, "top_k": 2},
                    headers=headers, timeout=300).json()
    assert raw["grasps"], raw["reason"]
    K = np.array([[scene.meta["intrinsics"]["fx"], 0, scene.meta["intrinsics"]["cx"]],
                  [0, scene.meta["intrinsics"]["fy"], scene.meta["intrinsics"]["cy"]],
                  [0, 0, 1]])  # as a ROS CameraInfo's K
    with GraspClient(server.url, token="secret") as client:
        session = client.session()
        for t in range(len(scene.depth)):
            out = session.add_view(_mm(scene.depth[t]), K, mask=scene.mask[t] >= 0,
                                   camera_pose=scene.camera_to_world[t], encoding="16UC1")
            assert out["view_index"] == t
        grasps = session.grasps(top_k=2)
        assert len(grasps) == len(raw["grasps"])
        for got, want in zip(grasps, raw["grasps"], strict=True):
            assert got.joints == want["joints_deg"]
            assert list(got.joints) == list(JOINT_NAMES)
            np.testing.assert_array_equal(got.joint_array, [want["joints_deg"][n]
                                                            for n in JOINT_NAMES])
            np.testing.assert_array_equal(got.palm_pose, want["palm_pose"])
            np.testing.assert_array_equal(got.palm_pose_world, want["palm_pose_world"])
            np.testing.assert_array_equal(got.pregrasp_pose_world, want["pregrasp_pose_world"])
            assert got.epsilon == want["epsilon"] and len(got.contacts) == len(want["contacts"])
        mesh = session.mesh()
        with client.session() as again:  # the same completion's input as a ready grid
            out = httpx.get(f"{server.url}/sessions/{session.id}/occupancy",
                            headers=headers).json()
            grid = VoxelGrid(VoxelGrid.unpack(base64.b64decode(out["data"])),
                             np.asarray(out["grid_to_camera"]))
            assert again.add_grid(grid)["observed_voxels"] == int(grid.occupancy.sum())
        assert len(mesh.faces) > 100 and session.info()["views"] == 12
        assert session.inspector_url.endswith(f"/sessions/{session.id}/view#token=secret")
        kept = session.id
    gone = httpx.get(f"{server.url}/sessions/{kept}", headers=headers)
    assert gone.status_code == 404  # the client deleted its session on exit


def test_a_session_on_a_table_keeps_its_plane_and_cuts_the_completion_there(server, scene):
    camera = scene.camera_to_world[0]  # the object floats about the world's origin
    with GraspClient(server.url, token="secret") as client:
        with client.session(support_plane=(0, 0, 2, 0)) as session:  # z = 0: its middle
            session.add_view(scene.depth[0], scene.meta["intrinsics"], mask=scene.mask[0] >= 0,
                             camera_pose=camera)
            np.testing.assert_allclose(session.info()["support_plane"], [0, 0, 1, 0])
            world = session.mesh().apply_transform(camera)  # nothing below the table
            assert world.vertices[:, 2].min() > -0.01 and world.vertices[:, 2].max() > 0.02
        with client.session(support_plane=(0, 0, 1, 0)) as session:
            with pytest.raises(InvalidRequest, match="camera_pose"):  # a plane needs poses
                session.add_view(scene.depth[0], scene.meta["intrinsics"])


def test_millimetres_and_metres_give_the_same_stored_view(server, scene):
    depth_mm = _mm(scene.depth[0])
    K = tuple(scene.meta["intrinsics"][k] for k in ("fx", "fy", "cx", "cy"))
    headers = {"Authorization": "Bearer secret"}
    stored = []
    with GraspClient(server.url, token="secret") as client:
        for depth in (depth_mm, (depth_mm / 1000.0).astype(np.float32)):
            with client.session() as session:
                session.add_view(depth, K, mask=scene.mask[0] >= 0)
                observed = httpx.get(f"{server.url}/sessions/{session.id}/observed",
                                     params={"format": "json"}, headers=headers).json()
                grid = httpx.get(f"{server.url}/sessions/{session.id}/occupancy",
                                 headers=headers).json()
                stored.append((np.asarray(observed["points"]), grid))
    (points_a, grid_a), (points_b, grid_b) = stored
    assert len(points_a) > 50
    np.testing.assert_allclose(points_a, points_b, atol=1e-6)
    np.testing.assert_allclose(grid_a["grid_to_camera"], grid_b["grid_to_camera"], atol=1e-6)
    assert grid_a["data"] == grid_b["data"]


def test_service_errors_raise_with_its_message(server, scene):
    with GraspClient(server.url, token="secret") as client, client.session() as session:
        session.add_view(_mm(scene.depth[0]), scene.meta["intrinsics"],
                         mask=np.zeros(scene.depth[0].shape, bool))  # nothing of the object
        with pytest.raises(NothingSeen, match="409"):
            session.grasps()
        session.add_view(_mm(scene.depth[0]), scene.meta["intrinsics"], mask=scene.mask[0] >= 0)
        with pytest.raises(InvalidRequest, match="n_candidates must be at most 8") as err:
            session.grasps(n_candidates=10_000)
        assert err.value.field == "n_candidates" and isinstance(err.value, ValueError)
        session.delete()
        assert session.id is None
    with GraspClient(server.url, token="wrong") as client:
        with pytest.raises(Unauthorized, match="401"):
            client.session().add_points(np.zeros((3, 3)) + [0, 0, 0.5])


def _recording(responses: list[httpx.Response]):
    """A transport that answers ``responses`` in turn and records every request it saw."""
    seen: list[httpx.Request] = []

    def handle(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return responses.pop(0)

    return httpx.MockTransport(handle), seen


def test_a_503_with_retry_after_is_retried_and_succeeds(monkeypatch):
    slept: list[float] = []
    monkeypatch.setattr(grasp_client.time, "sleep", slept.append)
    transport, seen = _recording([
        httpx.Response(503, headers={"Retry-After": "1"}, json={"detail": "planner busy"}),
        httpx.Response(200, json={"session_id": "s1", "view_index": 0, "observed_voxels": 3,
                                  "occupied_voxels": 9}),
    ])
    with GraspClient("http://robot-lab:8000", transport=transport) as client:
        session = client.session()
        assert session.add_points([[0, 0, 0.5], [0.01, 0, 0.5], [0, 0.01, 0.5]])["view_index"] == 0
        assert session.id == "s1" and slept == [1.0] and len(seen) == 2
        session.id = None  # nothing to delete on the fake service


def test_retries_are_bounded(monkeypatch):
    slept: list[float] = []
    monkeypatch.setattr(grasp_client.time, "sleep", slept.append)
    busy = [httpx.Response(503, headers={"Retry-After": "120"}, json={"detail": "store full"})
            for _ in range(3)]
    transport, seen = _recording(busy)
    with GraspClient("http://x", transport=transport, retries=2, max_wait=5) as client:
        with pytest.raises(grasp_client.ServiceError, match="503: store full"):
            client.health()
    assert len(seen) == 3 and slept == [5, 5]  # Retry-After capped by max_wait
    with GraspClient(f"http://127.0.0.1:{free_port()}", retries=2) as client:
        with pytest.raises(grasp_client.Unreachable, match="tried 3 times"):  # nothing listens
            client.health()
    assert slept[2:] == [0.5, 1.0]


@pytest.mark.parametrize(("call", "says"), [
    (lambda s: s.add_view(np.ones((4, 5), np.float32), np.eye(3), mask=np.ones((5, 4))),
     "mask must have the depth image's shape"),
    (lambda s: s.add_view(np.ones((4, 5), np.float32), np.eye(4)), "K must be 3×3"),
    (lambda s: s.add_view(np.ones((4, 5), np.float32), [[1, 0, 2], [0, 1, 2], [0, 1, 1]]),
     "pinhole camera matrix"),
    (lambda s: s.add_view(np.ones((4, 5), np.float32), (0, 1, 2, 2)), "fx, fy > 0"),
    (lambda s: s.add_view(np.ones((4, 5), np.float32), (1, 1, 2, 2), encoding="16UC1"),
     "holds mm"),
    (lambda s: s.add_view(np.ones((4, 5), np.int32), (1, 1, 2, 2)), "float metres or uint16"),
    (lambda s: s.add_view(np.ones(5, np.float32), (1, 1, 2, 2)), r"\(H, W\) image"),
    (lambda s: s.add_view(np.ones((4, 5), np.float32), (1, 1, 2, 2), camera_pose=np.eye(3)),
     r"camera_pose must have shape \(4, 4\)"),
        (lambda s: s.add_view(np.ones((4, 5), np.float32), (1, 1, 2, 2),
                              camera_pose=np.diag([2.0, 1, 1, 1])), "must be a rigid camera→world"),
    (lambda s: s.add_points(np.zeros((3, 2))), r"finite \(N, 3\)"),
    (lambda s: s.grasps(), "no view yet"),
])
def test_bad_input_raises_before_any_request(call, says):
    transport, seen = _recording([])
    with GraspClient("http://x", transport=transport) as client:
        with pytest.raises((InvalidRequest, NothingSeen), match=says):  # the documented ones
            call(client.session())
    assert seen == []
    with pytest.raises(InvalidRequest, match="support_plane"):
        GraspClient("http://x", transport=transport).session(support_plane=(0, 0, 0, 1))


def test_grasp_from_json_keeps_the_documented_joint_order():
    g = {"palm_pose": np.eye(4).tolist(), "palm_pose_world": None, "pregrasp_pose":
         np.eye(4).tolist(), "pregrasp_pose_world": None,
         "joints_deg": {name: float(i) for i, name in reversed(list(enumerate(JOINT_NAMES)))},
         "dofs_deg": [0, 1, 2, 3], "epsilon": 0.1, "force_epsilon": 0.2, "volume": 0.01,
         "palm_contact": True, "contacts": [{"link": "palm", "point": [0, 0, 0.1],
                                             "normal": [0, 0, 1]}]}
    grasp = Grasp.from_json(g)
    assert list(grasp.joints) == list(JOINT_NAMES)
    np.testing.assert_array_equal(grasp.joint_array, np.arange(8.0))
    assert grasp.palm_pose_world is None and grasp.contacts[0].link == "palm"


def test_a_robot_sends_a_label_image_and_the_grasps_keep_clear_of_the_other_objects(server):
    """Issue 61: a label image's other objects become the session's obstacles; the client says
    how many the grasps kept clear of, and refuses an obstacle mask of the wrong size."""
    from completion.depth_camera import Renderer
    from grasp.evaluate.clutter_scenes import clutter_scene

    renderer = Renderer()
    try:
        scene = clutter_scene(0, 0, renderer)
    finally:
        renderer.close()
    k = scene.intrinsics
    with GraspClient(server.url, token="secret") as client, \
            client.session(support_plane=[0.0, 0.0, 1.0, 0.0]) as session:
        for t in (0, 2):
            labels = np.where(scene.mask[t], 5, np.where(scene.others[t], 9, 0)).astype(np.uint8)
            session.add_view(scene.depth[t], (k.fx, k.fy, k.cx, k.cy), mask=labels,
                             object_label=5, camera_pose=scene.cameras[t])
        session.grasps(n_candidates=4)
        assert session.last_obstacle_voxels > 50
        with pytest.raises(InvalidRequest, match="obstacle_mask"):
            session.add_view(scene.depth[0], (k.fx, k.fy, k.cx, k.cy), mask=scene.mask[0],
                             obstacle_mask=np.ones((4, 4)))


def test_a_kept_session_outlives_the_with_blocks(server):
    """``keep=True``: the session stays on the service for its inspector page after the
    ``with`` blocks end, until it expires or is deleted; the others are deleted as before."""
    points = np.random.default_rng(0).normal(scale=0.02, size=(300, 3)) + [0.0, 0.0, 0.5]
    with GraspClient(server.url, token="secret") as client:
        with client.session(keep=True) as kept, client.session() as dropped:
            kept.add_points(points)
            dropped.add_points(points)
            ids = kept.id, dropped.id
    headers = {"Authorization": "Bearer secret"}
    assert httpx.get(f"{server.url}/sessions/{ids[0]}", headers=headers).status_code == 200
    assert httpx.get(f"{server.url}/sessions/{ids[1]}", headers=headers).status_code == 404
    with GraspClient(server.url, token="secret") as client:
        client.request("DELETE", f"/sessions/{ids[0]}")
