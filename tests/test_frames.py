"""A wrong frame never becomes a confident grasp (service/intake/frames.py): the seven frame
mistakes a robot integration makes, and the four views that show nothing, each a 422 naming the
mistake, through the real client against a real ``python -m service`` and as raw HTTP; the correct
views of the same scene give the same grasp with the checks on and off."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from service_helpers import Server

from grasp_client import GraspClient, InvalidRequest
from grasp_client.wire import SupportPlane, b64, depth_f32_m, png_bytes

TABLE_Z = 0.16  # the world's table lies at z = 0.16 m, so that d's sign matters
PLANE = (0.0, 0.0, 1.0, -TABLE_Z)


@pytest.fixture(scope="module")
def server(tmp_path_factory, tiny_model):
    tmp = tmp_path_factory.mktemp("frames")
    s = Server(tmp, tiny_model, tmp / "store.sqlite")
    yield s
    s.stop()


@pytest.fixture(scope="module")
def table_scene():
    """4 views of an object resting on a table (the tabletop condition, test split, sequence 0):
    depth (m), the object's mask, K, camera→world poses in a world whose table is z = 0.16."""
    from completion.scenes import make_sequence

    seq = make_sequence("tabletop", "test", 0, keep_depth=True)
    lift = np.eye(4)
    lift[2, 3] = TABLE_Z
    k = seq.meta["intrinsics"]
    K = np.array([[k["fx"], 0, k["cx"]], [0, k["fy"], k["cy"]], [0, 0, 1]])
    depths = [np.nan_to_num(d).astype(np.float32) for d in seq.depth[:4]]
    return depths, [m == 0 for m in seq.mask[:4]], K, [lift @ p for p in seq.camera_to_world[:4]]


def _mm(pose):
    out = pose.copy()
    out[:3, 3] *= 1000.0
    return out


# mistake -> (what changes: pose, plane or K), the field refused (the mistake's own, whichever check
# noticed it), words of the message
MISTAKES = {
    "translation in millimetres": ({"pose": _mm}, "camera_pose", "looks like millimetres"),
    "world→camera": ({"pose": np.linalg.inv}, "camera_pose", "world→camera"),
    "OpenGL camera": ({"pose": lambda p: p @ np.diag([1.0, -1.0, -1.0, 1.0])}, "camera_pose",
                      "OpenGL"),
    "plane in the camera frame": ({"plane": lambda p, pose: tuple(
        SupportPlane(p[:3], p[3]).transformed(pose).as_array())},
        "support_plane", "in the camera frame"),
    "plane's d with the wrong sign": ({"plane": lambda p, pose: (*p[:3], -p[3])},
                                      "support_plane", "wrong sign"),
    "plane's normal down": ({"plane": lambda p, pose: tuple(-np.array(p))}, "support_plane",
                            "normal points down"),
    "K as fx, cx, fy, cy": ({"K": lambda K: (K[0, 0], K[0, 2], K[1, 1], K[1, 2])}, "intrinsics",
                            "order fx, fy, cx, cy"),
}


@pytest.mark.parametrize("mistake", MISTAKES)
def test_a_frame_mistake_is_refused_and_named(server, table_scene, mistake):
    depths, masks, K, poses = table_scene
    change, field, words = MISTAKES[mistake]
    pose = change.get("pose", lambda p: p)(poses[0])
    plane = change.get("plane", lambda p, _: p)(PLANE, poses[0])
    k = change.get("K", lambda k: k)(K)
    with GraspClient(server.url) as client, client.session(plane) as session:
        with pytest.raises(InvalidRequest) as err:
            session.add_view(depths[0], k, mask=masks[0], camera_pose=pose)
        assert words in str(err.value), str(err.value)
        if field:
            assert err.value.field == field, (err.value.field, str(err.value))
        assert session.id is None  # nothing was stored
    fx_fy_cx_cy = np.ravel(k)[[0, 4, 2, 5]] if np.ndim(k) == 2 else k
    body = {"depth": depth_f32_m(depths[0]), "mask": b64(png_bytes(masks[0].astype(np.uint8))),
            "intrinsics": dict(zip(("fx", "fy", "cx", "cy"), map(float, fx_fy_cx_cy),
                                   strict=True)),
            "camera_pose": pose.tolist(), "support_plane": list(plane)}
    r = httpx.post(f"{server.url}/views", json=body, timeout=60)
    assert r.status_code == 422 and words in r.text, r.text


@pytest.mark.parametrize("mistake", ["world→camera", "OpenGL camera"])
def test_a_second_view_whose_pose_contradicts_the_first_is_refused(server, table_scene, mistake):
    """Without a support plane a single view cannot refute its pose; the second, from another
    pose, can: the object would lie elsewhere in the world. The session keeps its first view."""
    depths, masks, K, poses = table_scene
    change = MISTAKES[mistake][0]["pose"]
    with GraspClient(server.url) as client, client.session() as session:
        session.add_view(depths[0], K, mask=masks[0], camera_pose=poses[0])
        with pytest.raises(InvalidRequest) as err:
            session.add_view(depths[1], K, mask=masks[1], camera_pose=change(poses[1]))
        assert "the views disagree" in str(err.value) and MISTAKES[mistake][2] in str(err.value)
        assert err.value.field == "camera_pose"
        assert session.info()["views"] == 1


def test_views_that_show_nothing_say_why(server, table_scene):
    depths, masks, K, poses = table_scene
    labels = np.where(masks[0], 2, 1).astype(np.uint8)
    with GraspClient(server.url) as client, client.session() as session:
        with pytest.raises(InvalidRequest, match="object_label 7 is not in the label image"):
            session.add_view(depths[0], K, mask=labels, object_label=7)
        with pytest.raises(InvalidRequest, match="metres cast to uint16"):
            session.add_view(depths[0].astype(np.uint16), K, mask=masks[0])
        with pytest.raises(InvalidRequest, match="no valid pixel"):
            session.add_view(np.full_like(depths[0], np.nan), K)
        with pytest.raises(InvalidRequest, match="points is empty"):
            session.add_points(np.zeros((0, 3)))
        with pytest.raises(InvalidRequest, match="none of the mask's"):
            session.add_view(np.where(masks[0], 0.0, depths[0]).astype(np.float32), K,
                             mask=masks[0])
        assert session.id is None


def test_the_correct_views_give_the_same_grasp_with_the_checks_on_and_off(server, table_scene):
    depths, masks, K, poses = table_scene
    grasps = []
    for check in (True, False):
        with GraspClient(server.url) as client, client.session(PLANE) as session:
            for depth, mask, pose in zip(depths, masks, poses, strict=True):
                session.add_view(depth, K, mask=mask, camera_pose=pose, check_frames=check)
            grasps.append([g.palm_pose_world for g in session.grasps(top_k=1)])
    assert len(grasps[0]) == len(grasps[1])
    for a, b in zip(*grasps, strict=True):
        np.testing.assert_allclose(a, b)


def test_a_caller_who_knows_better_turns_a_check_off(server, table_scene):
    depths, masks, K, poses = table_scene
    with GraspClient(server.url) as client, client.session((0.0, 0.0, 1.0, TABLE_Z)) as session:
        with pytest.raises(InvalidRequest, match="wrong sign"):
            session.add_view(depths[0], K, mask=masks[0], camera_pose=poses[0])
        session.add_view(depths[0], K, mask=masks[0], camera_pose=poses[0], check_frames=False)
        assert session.info()["views"] == 1


def test_with_the_service_stopped_every_call_raises_a_client_exception(free_url, table_scene):
    """No httpx type reaches robot code: a refused connection, after the retries, is
    grasp_client.Unreachable (a ServiceError and a ConnectionError)."""
    import grasp_client

    depths, masks, K, poses = table_scene
    calls = {
        "health": lambda c, s: c.health(),
        "add_view": lambda c, s: s.add_view(depths[0], K, mask=masks[0], camera_pose=poses[0]),
        "add_points": lambda c, s: s.add_points(np.array([[0.0, 0.0, 0.5]])),
        "grasps": lambda c, s: s.grasps(),
        "info": lambda c, s: s.info(),
        "request": lambda c, s: c.request("GET", "/sessions/x"),
    }
    with GraspClient(free_url, retries=1, max_wait=0.01) as client:
        session = client.session()
        for name, call in calls.items():
            with pytest.raises(grasp_client.ServiceError) as err:
                call(client, session)
            assert not isinstance(err.value, httpx.HTTPError), name
            if name not in ("grasps", "info"):  # those need a view first: NothingSeen
                assert isinstance(err.value, grasp_client.Unreachable), name
                assert isinstance(err.value, ConnectionError) and free_url in str(err.value)


def test_ros_camera_info_and_single_channel_images_are_accepted(server, table_scene):
    """K as ROS's flat CameraInfo.k (9 numbers) or .p (3×4), depth and mask as (H, W, 1)."""
    depths, masks, K, poses = table_scene
    P = np.hstack([K, np.zeros((3, 1))])
    with GraspClient(server.url) as client, client.session(PLANE) as session:
        for k in (K.ravel().tolist(), P, P.ravel()):
            out = session.add_view(depths[0][..., None], k, mask=masks[0][..., None],
                                   camera_pose=poses[0])
            assert out["observed_voxels"] > 100
        with pytest.raises(InvalidRequest, match="3×4 P must end"):
            session.add_view(depths[0], np.vstack([K, [1, 0, 0]]).T[:3], camera_pose=poses[0])


@pytest.fixture
def free_url():
    from service_helpers import free_port

    return f"http://127.0.0.1:{free_port()}"


def test_a_view_whose_background_is_all_table_is_accepted(server, table_scene):
    """A camera that sees nothing but the table around the object (the background's heights
    within a few mm of the plane), the object's lowest point above the tolerance: accepted (a
    regression: a flat background once counted as no table)."""
    from service.load import make_bodies

    bodies = make_bodies(4, 2, 1, "tabletop")[2]  # an object whose lowest seen point is 3.7 cm up
    sid = None
    for body in bodies:
        r = httpx.post(f"{server.url}/views", json=body | ({"session_id": sid} if sid else {}),
                       timeout=60)
        assert r.status_code == 200, r.text
        sid = r.json()["session_id"]


def test_a_plane_given_on_get_grasp_passes_the_same_checks(server, table_scene):
    """A table raised 6 cm is refused on GET /grasp as on a view, on the query's field, and the
    session keeps the plane it had: the next correct view is accepted."""
    depths, masks, K, poses = table_scene
    raised = ",".join(map(str, (0.0, 0.0, 1.0, -(TABLE_Z + 0.06))))
    right = ",".join(map(str, PLANE))
    with GraspClient(server.url) as client, client.session() as session:
        session.add_view(depths[0], K, mask=masks[0], camera_pose=poses[0])
        for kept in (None, list(PLANE)):
            r = httpx.get(f"{server.url}/grasp", timeout=60,
                          params={"session_id": session.id, "support_plane": raised})
            assert r.status_code == 422, r.text
            detail = r.json()["detail"][0]
            assert detail["loc"] == ["query", "support_plane"], detail
            assert "below the support plane" in detail["msg"], detail
            assert session.info()["support_plane"] == kept  # nothing stored changed
            r = httpx.get(f"{server.url}/grasp", timeout=60,
                          params={"session_id": session.id, "support_plane": right})
            assert r.status_code == 200, r.text
        session.add_view(depths[1], K, mask=masks[1], camera_pose=poses[1])
        assert session.info()["views"] == 2
