"""What the service tests share: a tiny model, settings, request helpers, a real server.

A tiny untrained MVP (saved to a temporary checkpoint) stands in for the shipped weights; its
completion is the same for every input (a full grid, so the mesh is a box around the object),
which is all the routes need. Numbers are compared with a ``CompletionStream`` fed the same
decoded views in-process (:func:`reference`). :class:`Server` runs ``python -m service`` in its
own process on 127.0.0.1, as users run it. The fixtures ``tiny_model``, ``scene`` and ``client``
live in tests/conftest.py.
"""

from __future__ import annotations

import base64
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import torch
from fastapi.testclient import TestClient

from completion.config import ModelConfig
from completion.grid import VoxelGrid
from completion.model import build_model, load_model, save_checkpoint
from completion.stream import CompletionStream
from service.api.schemas import ViewIn
from service.intake.inputs import decode_view
from service.settings import Settings

TINY = ModelConfig(channels=(4, 8, 8), embed_dim=16, n_heads=2, n_features=8)
MAX_POINTS = 2000
MAX_PIXELS = 320 * 240
MAX_BODY = 2 * 1024 * 1024
JOINT_RANGES = {"spread": (0.0, 180.0), "prox": (0.0, 140.0), "dist": (0.0, 48.0)}


def save_tiny(path, **config) -> str:
    save_checkpoint(build_model(TINY.replace(**config)), path)
    return str(path)


def settings(tmp_path, model: str, **overrides) -> Settings:
    values = dict(
        model=model,
        store_path=tmp_path / "store.sqlite",
        max_points=MAX_POINTS,
        max_image_pixels=MAX_PIXELS,
        max_body_bytes=MAX_BODY,
        n_candidates=4,
        max_candidates=16,
        torch_threads=torch.get_num_threads(),  # leave the test process as it was
        planning_processes=False,  # the real-server tests plan in processes
    )
    return Settings(**(values | overrides))


def points_view(n: int = 300, seed: int = 0, centre=(0.0, 0.0, 0.5)) -> dict:
    """A blob of ~5 cm in front of the camera."""
    rng = np.random.default_rng(seed)
    return {"points": (rng.normal(scale=0.02, size=(n, 3)) + centre).tolist()}


def hidden_view() -> dict:
    """A view in which the object is hidden: a 32 × 24 depth image (a wall 0.5 m away) whose
    mask is empty."""
    from grasp_client.wire import b64, depth_f32_m, png_bytes

    depth = np.full((24, 32), 0.5, dtype=np.float32)
    return {"depth": depth_f32_m(depth), "intrinsics": {"fx": 28.0, "fy": 28.0, "cx": 15.5,
                                                        "cy": 11.5},
            "mask": b64(png_bytes(np.zeros((24, 32), dtype=np.uint8)))}


def new_session(client: TestClient, body: dict | None = None) -> str:
    r = client.post("/views", json=body or points_view())
    assert r.status_code == 200, r.text
    return r.json()["session_id"]


def reference(model_path: str, bodies: list[dict]) -> CompletionStream:
    """The same views through an in-process CompletionStream (no HTTP, no store)."""
    stream = CompletionStream(load_model(model_path))
    for body in bodies:
        limits = Settings(max_image_pixels=10**9, max_points=10**9).decode_limits()
        stream.add_view(decode_view(ViewIn.model_validate(body), limits))
    return stream


def occupancy(client: TestClient, session_id: str) -> tuple[np.ndarray, dict]:
    r = client.get(f"/sessions/{session_id}/occupancy")
    assert r.status_code == 200, r.text
    body = r.json()
    return VoxelGrid.unpack(base64.b64decode(body["data"])), body


def stored_state(store_path, session_id: str) -> bytes:
    with sqlite3.connect(store_path) as con:
        (state,) = con.execute("SELECT state FROM sessions WHERE id = ?", (session_id,)).fetchone()
    return bytes(state)


def check_grasp(g: dict) -> None:
    """Joints named and within the BarrettHand's ranges; a rigid palm pose; contacts."""
    assert list(g["joints_deg"]) == [
        "f1_spread", "f1_prox", "f1_dist", "f2_spread", "f2_prox", "f2_dist", "f3_prox", "f3_dist",
    ]  # fmt: skip
    for name, value in g["joints_deg"].items():
        lo, hi = JOINT_RANGES[name.split("_")[1]]
        assert lo - 1e-6 <= value <= hi + 1e-6, (name, value)
    assert g["joints_deg"]["f1_spread"] == g["joints_deg"]["f2_spread"]
    assert len(g["dofs_deg"]) == 4 and g["dofs_deg"][0] == g["joints_deg"]["f1_spread"]
    pose = np.asarray(g["palm_pose"])
    np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-6)
    np.testing.assert_allclose(pose[3], [0, 0, 0, 1])
    before = np.asarray(g["pregrasp_pose"])  # the same orientation, 0.2 m back along −z
    np.testing.assert_allclose(before[:3, :3], pose[:3, :3], atol=1e-12)
    np.testing.assert_allclose(before[:3, 3], pose[:3, 3] - 0.2 * pose[:3, 2], atol=1e-9)
    if g["palm_pose_world"] is not None:
        world = np.asarray(g["palm_pose_world"]) @ np.linalg.inv(pose)  # camera→world
        np.testing.assert_allclose(g["pregrasp_pose_world"], world @ before, atol=1e-9)
    else:
        assert g["pregrasp_pose_world"] is None
    assert g["epsilon"] > 0 and g["volume"] > 0
    assert g["contacts"] and all(len(c["point"]) == 3 for c in g["contacts"])


# --------------------------------------------------------------------------------- real server
# ``python -m service`` in its own process on 127.0.0.1, as users run it.

REPO = Path(__file__).resolve().parents[1]
STARTUP_S = 240.0  # a loaded CI machine imports torch slowly


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """``python -m service --port P`` with GRASP_* settings; SIGKILL-able."""

    def __init__(self, tmp_path: Path, model: str, store: Path, **settings) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.store = store
        self.log = tmp_path / f"server-{self.port}.log"
        env = os.environ | {
            "GRASP_MODEL": model,
            "GRASP_STORE_PATH": str(store),
            "GRASP_N_CANDIDATES": "4",
            "GRASP_MAX_CANDIDATES": "8",
            "GRASP_INFERENCE_WORKERS": "2",
            "GRASP_PLANNING_WORKERS": "1",
        }
        env |= {f"GRASP_{k.upper()}": str(v) for k, v in settings.items()}
        with open(self.log, "wb") as log:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "service", "--port", str(self.port)],
                cwd=REPO,
                env=env,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        deadline = time.monotonic() + STARTUP_S
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"the server exited: {self.log.read_text()[-2000:]}")
            try:
                if httpx.get(f"{self.url}/healthz", timeout=2).status_code == 200:
                    return
            except httpx.TransportError:
                time.sleep(0.2)
        self.kill()
        raise RuntimeError(f"the server did not start in {STARTUP_S} s: {self.log.read_text()}")

    def kill(self) -> None:
        """SIGKILL: no shutdown handlers run."""
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(timeout=30)

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.kill()


def post_views(url: str, bodies: list[dict], session_id: str | None = None, *,
               headers: dict | None = None) -> tuple[str, list]:
    indices = []
    with httpx.Client(base_url=url, timeout=120, headers=headers) as client:
        for body in bodies:
            payload = body if session_id is None else body | {"session_id": session_id}
            r = client.post("/views", json=payload)
            assert r.status_code == 200, r.text
            session_id = r.json()["session_id"]
            indices.append(r.json()["view_index"])
    return session_id, indices


def post_concurrently(urls: list[str], threads: int, per_thread: int) -> tuple[str, list[dict]]:
    """Start a session, then let ``threads`` clients (client t talks to ``urls[t % len]``) post
    ``per_thread`` views each, all at once. Checks that every view was answered with its own
    index; returns the session and the bodies in the order the server applied them."""
    bodies = {
        (t, i): points_view(seed=100 * t + i) for t in range(threads) for i in range(per_thread)
    }
    sid, _ = post_views(urls[0], [points_view(seed=999)])
    answers: dict[int, tuple[int, int]] = {}
    errors: list[str] = []
    start = threading.Barrier(threads)

    def worker(t: int) -> None:
        with httpx.Client(base_url=urls[t % len(urls)], timeout=120) as client:
            start.wait()
            for i in range(per_thread):
                r = client.post("/views", json=bodies[t, i] | {"session_id": sid})
                if r.status_code != 200:
                    errors.append(r.text)
                    continue
                answers[r.json()["view_index"]] = (t, i)

    pool = [threading.Thread(target=worker, args=(t,)) for t in range(threads)]
    for th in pool:
        th.start()
    for th in pool:
        th.join()
    assert not errors
    n = threads * per_thread + 1
    assert sorted(answers) == list(range(1, n))  # each index exactly once (0 was the first view)
    return sid, [points_view(seed=999)] + [bodies[answers[k]] for k in range(1, n)]
