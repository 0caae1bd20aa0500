"""The neighbours a robot's views show, kept by the session as obstacles (issue 61): depth views
with the target's mask (or label image), a camera pose and a table; the obstacles accumulate in
the world frame across views, outlive a restart, and reach the planner and the inspector."""

from __future__ import annotations

import base64

import numpy as np
import pytest
from fastapi.testclient import TestClient
from service_helpers import settings

from grasp_client.wire import b64, depth_f32_m, png_bytes
from service.app import create_app

TABLE = [0.0, 0.0, 1.0, 0.0]


@pytest.fixture(scope="module")
def clutter():
    """The clutter table's first scene: a target, its neighbours and a pan of 4 views."""
    from completion.depth_camera import Renderer
    from grasp.evaluate.clutter_scenes import clutter_scene

    renderer = Renderer()
    try:
        return clutter_scene(0, 0, renderer)
    finally:
        renderer.close()


def view(scene, t: int, *, label: bool = False, **extra) -> dict:
    k = scene.intrinsics
    if label:  # a label image: 7 the target, 3 the neighbours, 0 the rest
        labels = np.where(scene.mask[t], 7, np.where(scene.others[t], 3, 0)).astype(np.uint8)
        masks = {"mask": b64(png_bytes(labels)), "object_label": 7}
    else:
        masks = {"mask": b64(png_bytes(scene.mask[t].astype(np.uint8)))}
    return {"depth": depth_f32_m(scene.depth[t].astype(np.float32)),
            "intrinsics": {"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy},
            "camera_pose": scene.cameras[t].tolist(), "support_plane": TABLE,
            **masks, **extra}


def _obstacles_world(client, sid: str) -> tuple[np.ndarray, dict]:
    plan = client.get("/grasp", params={"session_id": sid, "n_candidates": 4}).json()
    seen = client.get(f"/sessions/{sid}/observed").json()  # float32 rows, base64
    local = np.frombuffer(base64.b64decode(seen["obstacles"]), "<f4").reshape(-1, 3)
    listed = client.get(f"/sessions/{sid}/observed", params={"format": "json"}).json()
    assert seen["n_obstacles"] == len(listed["obstacles"]) == len(local)
    np.testing.assert_allclose(local, np.asarray(listed["obstacles"]).reshape(-1, 3), atol=1e-6)
    camera = np.asarray(plan["camera_pose"])
    return local @ camera[:3, :3].T + camera[:3, 3], plan


def test_obstacles_accumulate_across_views_in_the_world_frame_and_outlive_a_restart(
        tmp_path, tiny_model, clutter):
    from trimesh.proximity import closest_point

    config = settings(tmp_path, tiny_model, max_points=500_000)
    with TestClient(create_app(config)) as client:
        first = client.post("/views", json=view(clutter, 0, label=True))
        assert first.status_code == 200, first.text
        sid = first.json()["session_id"]
        once, plan = _obstacles_world(client, sid)
        assert plan["obstacle_voxels"] == len(once) > 50
        r = client.post("/views", json=view(clutter, 2) | {"session_id": sid})
        assert r.status_code == 200, r.text
        twice, plan = _obstacles_world(client, sid)
        assert plan["obstacle_voxels"] == len(twice) > len(once)  # another side seen
        # every obstacle voxel lies on a neighbour (the sensor's noise, the voxel's size)
        to_neighbours = np.min([closest_point(m, twice)[1] for m in clutter.neighbours], axis=0)
        assert np.percentile(to_neighbours, 95) < 0.015
        assert (closest_point(clutter.target, twice)[1] > 0.01).all()
    with TestClient(create_app(config)) as client:  # the same store, a new server
        again, plan = _obstacles_world(client, sid)
        assert plan["obstacle_voxels"] == len(twice)
        assert np.allclose(np.sort(again, axis=0), np.sort(twice, axis=0), atol=1e-6)


def test_a_view_may_send_its_obstacles_or_none(tmp_path, tiny_model, clutter):
    config = settings(tmp_path, tiny_model, max_points=500_000)
    with TestClient(create_app(config)) as client:
        none = client.post("/views", json=view(clutter, 0, obstacles=False)).json()
        assert _obstacles_world(client, none["session_id"])[1]["obstacle_voxels"] == 0
        own = view(clutter, 0, obstacle_mask=b64(png_bytes(clutter.others[0].astype(np.uint8))))
        sent = client.post("/views", json=own).json()
        assert _obstacles_world(client, sent["session_id"])[1]["obstacle_voxels"] > 50
        wrong = view(clutter, 0, obstacle_mask=b64(png_bytes(np.ones((4, 4), np.uint8))))
        r = client.post("/views", json=wrong)
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "obstacle_mask"]
        # a label image in which the target's label is absent
        r = client.post("/views", json=view(clutter, 0, label=True) | {"object_label": 9})
        assert r.status_code == 422 and "9" in r.text
        r = client.post("/views", json={"points": [[0, 0, 0.5]], "obstacle_mask": "x"})
        assert r.status_code == 422 and "go with depth only" in r.text


@pytest.mark.slow
def test_a_session_keeps_its_obstacles_through_a_sigkill(tmp_path, tiny_model, clutter):
    """Issue 61's bar: sessions with obstacles survive a restart (kill -9) with their obstacles."""
    import httpx
    from service_helpers import Server

    store = tmp_path / "store.sqlite"
    options = {"planning_processes": "false", "max_points": 500_000}

    def voxels(server, sid) -> int:
        r = httpx.get(f"{server.url}/grasp", params={"session_id": sid, "n_candidates": 4},
                      timeout=300)
        return r.json()["obstacle_voxels"]

    first = Server(tmp_path, tiny_model, store, **options)
    try:
        sid = httpx.post(f"{first.url}/views", json=view(clutter, 0, label=True),
                         timeout=60).json()["session_id"]
        before = voxels(first, sid)
    finally:
        first.kill()
    second = Server(tmp_path, tiny_model, store, **options)
    try:
        assert voxels(second, sid) == before > 50
        r = httpx.post(f"{second.url}/views", json=view(clutter, 2) | {"session_id": sid},
                       timeout=60)
        assert r.status_code == 200 and voxels(second, sid) > before
    finally:
        second.stop()


def test_obstacles_at_the_cap_are_stored_compactly_and_exactly(clutter):
    """A session at the obstacle cap (the neighbours' whole surfaces, far more than a camera
    sees) stores them in under 200 kB, and reads back the same voxels; a state stored before
    they were packed still reads."""
    import io

    from service_helpers import TINY
    from trimesh.sample import sample_surface

    from completion.model import build_model
    from completion.stream import MAX_OBSTACLE_VOXELS, CompletionStream

    stream = CompletionStream(build_model(TINY))
    bare = len(stream.to_bytes())
    rng = np.random.default_rng(0)
    for mesh in clutter.neighbours:  # copies on a grid across the table: beyond the cap
        for dx in np.linspace(-0.4, 0.4, 6):
            for dy in np.linspace(-0.4, 0.4, 6):
                stream.add_obstacles(sample_surface(mesh, 20_000, seed=rng)[0] + [dx, dy, 0.0])
    assert len(stream.obstacle_keys) == MAX_OBSTACLE_VOXELS
    data = stream.to_bytes()
    assert len(data) - bare < 200_000, len(data) - bare
    again = CompletionStream.from_bytes(build_model(TINY), data)
    np.testing.assert_array_equal(again.obstacle_keys, stream.obstacle_keys)
    with np.load(io.BytesIO(data)) as z:  # the form before packing: keys as int32 rows
        arrays = {k: z[k] for k in z.files if k != "obstacles_packed"}
    old = io.BytesIO()
    np.savez(old, **arrays, obstacle_keys=stream.obstacle_keys)
    np.testing.assert_array_equal(
        CompletionStream.from_bytes(build_model(TINY), old.getvalue()).obstacle_keys,
        stream.obstacle_keys)
