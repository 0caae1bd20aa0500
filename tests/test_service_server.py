"""The real thing: ``python -m service`` in its own process on 127.0.0.1, as users run it.

SIGKILL and restart, eight concurrent clients on one session, the load generator; a tiny untrained
MVP stands in for the shipped weights (tests/service_helpers.py).
"""

from __future__ import annotations

import subprocess
import sys

import httpx
import numpy as np
import pytest
from service_helpers import (
    REPO,
    Server,
    check_grasp,
    post_concurrently,
    post_views,
    reference,
    stored_state,
)

from completion.model import load_model
from completion.stream import CompletionStream
from service.load import scene_views


@pytest.fixture(scope="module")
def server(tmp_path_factory, tiny_model):
    tmp = tmp_path_factory.mktemp("server")
    s = Server(tmp, tiny_model, tmp / "store.sqlite")
    yield s
    s.stop()


@pytest.mark.slow
def test_stream_a_scene_then_grasp_and_mesh(server, scene):
    bodies = scene_views(scene)
    assert len(bodies) == 12
    sid, indices = post_views(server.url, bodies)
    assert indices == list(range(12))
    r = httpx.get(f"{server.url}/grasp", params={"session_id": sid, "n_candidates": 8}, timeout=300)
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["views"] == 12 and out["grasps"], out["reason"]
    for g in out["grasps"]:
        check_grasp(g)
        np.testing.assert_allclose(
            g["palm_pose_world"], scene.camera_to_world[11] @ np.asarray(g["palm_pose"]), atol=1e-9
        )
    for fmt in ("ply", "glb"):
        r = httpx.get(f"{server.url}/sessions/{sid}/mesh", params={"format": fmt}, timeout=60)
        assert r.status_code == 200 and len(r.content) > 1000
    from completion.mesh import load_mesh_bytes

    assert load_mesh_bytes(r.content, "glb").is_watertight


@pytest.mark.slow
def test_restart_after_sigkill_continues_the_stream(tmp_path, tiny_model, scene):
    bodies = scene_views(scene)
    store = tmp_path / "store.sqlite"
    no_planner = {"planning_processes": "false"}  # nothing to plan: start no planner process
    first = Server(tmp_path, tiny_model, store, **no_planner)
    try:
        sid, indices = post_views(first.url, bodies[:6])
    finally:
        first.kill()
    second = Server(tmp_path, tiny_model, store, **no_planner)
    try:
        _, more = post_views(second.url, bodies[6:], session_id=sid)
        info = httpx.get(f"{second.url}/sessions/{sid}").json()
    finally:
        second.stop()
    assert indices + more == list(range(12)) and info["views"] == 12
    resumed = CompletionStream.from_bytes(load_model(tiny_model), stored_state(store, sid))
    uninterrupted = reference(tiny_model, bodies)
    a, b = resumed.completion(), uninterrupted.completion()
    np.testing.assert_allclose(a.probabilities, b.probabilities, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(a.grid_to_camera, b.grid_to_camera)
    np.testing.assert_array_equal(resumed.camera_to_world, scene.camera_to_world[11])

@pytest.mark.slow
def test_concurrent_views_to_one_session_are_all_applied(server, tiny_model):
    sid, order = post_concurrently([server.url], threads=8, per_thread=3)
    assert httpx.get(f"{server.url}/sessions/{sid}").json()["views"] == len(order)
    # The stored state is the sequential replay of the views in the order they were applied.
    stored = stored_state(server.store, sid)
    assert stored == reference(tiny_model, order).to_bytes()


@pytest.mark.slow
def test_load_generator(server):
    r = subprocess.run(
        [sys.executable, "-m", "service.load", "--url", server.url, "--sessions", "3",
         "--views", "3", "--concurrency", "3", "--scenes", "1", "--n-candidates", "4"],
        cwd=REPO, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr
    assert "POST /views" in r.stdout and "GET /grasp" in r.stdout
    assert "views sent 9, lost 0" in r.stdout
    r = subprocess.run(  # objects on a table, the plane given with each session's first view
        [sys.executable, "-m", "service.load", "--url", server.url, "--sessions", "1",
         "--views", "2", "--scenes", "1", "--n-candidates", "4", "--condition", "tabletop",
         "--grasp-every-view"],
        cwd=REPO, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert r.returncode == 0 and "views sent 2, lost 0" in r.stdout, r.stdout + r.stderr
    assert httpx.get(f"{server.url}/healthz").json()["sessions"] >= 0
    r = subprocess.run(
        [sys.executable, "-m", "service.load", "--url", "http://10.1.2.3:8000"],
        cwd=REPO, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 2 and "only talks to loopback hosts" in r.stderr
