"""The front door: bodies parsed off the event loop, and an API document that matches the code
(schemathesis with every check, against a real server)."""

from __future__ import annotations

import asyncio
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from service_helpers import Server, points_view, save_tiny, settings

from service.app import create_app
from service.intake import parsing
from service.intake.parsing import BodyParser
from service.settings import Settings

CONFIG = Path(__file__).resolve().parent / "schemathesis.toml"


def test_document_matches_the_settings(tmp_path):
    model = save_tiny(tmp_path / "tiny.pt")
    with TestClient(create_app(settings(tmp_path, model, max_candidates=16))) as client:
        doc = client.get("/openapi.json").json()
        assert "securitySchemes" not in doc.get("components", {})
        assert all("security" not in op for ops in doc["paths"].values() for op in ops.values())
        n = next(p for p in doc["paths"]["/grasp"]["get"]["parameters"]
                 if p["name"] == "n_candidates")  # fmt: skip
        assert {"type": "integer", "minimum": 1, "maximum": 16}.items() <= next(
            o for o in n["schema"]["anyOf"] if o.get("type") == "integer").items()
        view = doc["components"]["schemas"]["ViewIn"]
        assert [sorted(o["required"]) for o in view["oneOf"]] == [
            ["points"], ["depth", "intrinsics"], ["grid"]]
        # what the server refuses as a pair, the schema says too
        assert [(r["if"]["required"], r["then"]["required"]) for r in view["allOf"]] == [
            (["support_plane"], ["camera_pose"]), (["object_label"], ["mask"])]
        body = doc["paths"]["/views"]["post"]["requestBody"]["content"]["application/json"]
        assert body["schema"] == {"$ref": "#/components/schemas/ViewIn"}
        r = client.put("/sessions/abc")
        assert r.status_code == 405 and r.headers["allow"] == "DELETE, GET"
    with TestClient(create_app(settings(tmp_path, model, token="s3cret"))) as client:
        doc = client.get("/openapi.json").json()
        assert "HTTPBearer" in doc["components"]["securitySchemes"]


def test_big_bodies_are_parsed_in_a_worker_process(monkeypatch):
    """The same answers from the process pool as from the thread, errors included."""
    body = httpx.Request("POST", "http://x", json=points_view(n=500)).content
    bad = httpx.Request("POST", "http://x", json={"points": [[0, 0, -1]]}).content
    s = Settings(max_image_pixels=10**6, max_points=10**6)
    parser = BodyParser(1, limits=s.decode_limits(), at_once=2, max_body_bytes=s.max_body_bytes,
                        body_memory=s.body_memory_bytes, decode_memory=s.decode_memory_bytes,
                        memory_wait_s=s.memory_wait_s)

    async def both(raw: bytes):
        answers = []
        for threshold in (10**9, 0):  # thread, then process
            monkeypatch.setattr(parsing, "IN_PROCESS_BYTES", threshold)
            try:
                answers.append(await parser.parse(raw, "application/json"))
            except Exception as exc:  # noqa: BLE001 - compared below
                answers.append(exc)
        return answers

    try:
        thread, process = asyncio.run(both(body))
        np.testing.assert_array_equal(thread.view.points, process.view.points)
        assert thread.session_id is process.session_id is None
        thread, process = asyncio.run(both(bad))
        assert type(thread) is type(process) and thread.errors() == process.errors()
        assert "in front of the camera" in thread.errors()[0]["msg"]
    finally:
        parser.close()


@pytest.fixture(scope="module")
def big_server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("front")
    model = save_tiny(tmp / "tiny.pt")
    s = Server(tmp, model, tmp / "store.sqlite", max_points=1_000_000,
               max_body_bytes=64 * 1024 * 1024, planning_processes="false")  # fmt: skip
    yield s
    s.stop()


@pytest.mark.slow
def test_healthz_answers_while_a_huge_body_is_parsed(big_server):
    rng = np.random.default_rng(0)
    points = rng.normal(scale=0.02, size=(1_000_000, 3)) + (0, 0, 0.5)
    raw = httpx.Request("POST", "http://x", json={"points": points.round(6).tolist()}).content
    assert len(raw) > 25e6
    answer: dict = {}

    def post() -> None:
        r = httpx.post(f"{big_server.url}/views", content=raw, timeout=300,
                       headers={"content-type": "application/json"})  # fmt: skip
        answer["status"], answer["body"] = r.status_code, r.json()

    latencies = []
    with httpx.Client(base_url=big_server.url, timeout=30) as client:
        client.get("/healthz")  # connection open
        worker = threading.Thread(target=post)
        worker.start()
        while worker.is_alive():
            t0 = time.perf_counter()
            assert client.get("/healthz").status_code == 200
            latencies.append(time.perf_counter() - t0)
            time.sleep(0.05)
        worker.join()
    assert answer["status"] == 200, answer
    assert answer["body"]["observed_voxels"] > 0
    assert len(latencies) >= 10  # the POST took a while: the probes overlapped its parsing
    print(f"/healthz during a {len(raw) / 1e6:.0f} MB POST: {len(latencies)} probes, max "
          f"{max(latencies) * 1e3:.0f} ms, median {np.median(latencies) * 1e3:.0f} ms")
    assert max(latencies) < 0.3


@pytest.mark.slow
def test_schemathesis_every_check_is_clean(big_server, tmp_path):
    """``schemathesis run --checks all`` against the real server finds nothing (see
    tests/schemathesis.toml for why 422 may answer schema-valid data)."""
    httpx.post(f"{big_server.url}/views", json=points_view(), timeout=60)  # a live session
    done = subprocess.run(
        [str(Path(sys.executable).parent / "schemathesis"), "--config-file", str(CONFIG), "run",
         f"{big_server.url}/openapi.json", "--checks", "all", "--max-examples", "20",
         "--workers", "1", "--seed", "1", "--no-color"],
        cwd=tmp_path, capture_output=True, text=True, timeout=1200,  # its cache goes there
    )  # fmt: skip
    tail = done.stdout[-6000:]
    assert done.returncode == 0, tail
    assert "passed" in tail and "failures" not in tail.lower(), tail


def test_a_key_given_twice_is_refused_and_changes_nothing(client):
    """json.loads keeps the last of two equal keys: a view meant for no session (or another) would
    land in the real one. Each key once, or 400 naming it."""
    first = client.post("/views", json=points_view())
    sid = first.json()["session_id"]
    body = (f'{{"session_id": "nope", "session_id": "{sid}", "points": [[0, 0, 0.5], '
            '[0.01, 0, 0.5], [0, 0.01, 0.5]]}')
    r = client.post("/views", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 400 and "'session_id' appears twice" in r.json()["detail"]
    r = client.post("/views", content='{"depth": {"width": 2, "width": 3}}',
                    headers={"content-type": "application/json"})
    assert r.status_code == 400 and "'width' appears twice" in r.json()["detail"]
    assert client.get(f"/sessions/{sid}").json()["views"] == 1


@pytest.fixture(scope="module")
def slow_planner(tmp_path_factory):
    """Plans that take seconds: every one of up to 512 candidates autograsped."""
    tmp = tmp_path_factory.mktemp("races")
    s = Server(tmp, save_tiny(tmp / "tiny.pt"), tmp / "store.sqlite", max_candidates=512,
               plan_budget=512)
    yield s
    s.stop()


def _session(url: str) -> str:
    return httpx.post(f"{url}/views", json=points_view(), timeout=60).json()["session_id"]


def test_identical_concurrent_plans_are_computed_once(slow_planner):
    sid = _session(slow_planner.url)
    params = {"session_id": sid, "n_candidates": 48}
    answers: list[httpx.Response] = []

    def ask() -> None:
        answers.append(httpx.get(f"{slow_planner.url}/grasp", params=params, timeout=300))

    threads = [threading.Thread(target=ask) for _ in range(20)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert [r.status_code for r in answers] == [200] * 20  # none turned away (503)
    bodies = [r.json() for r in answers]
    assert sum(not b["cached"] for b in bodies) == 1  # one plan; the others shared it
    assert all(b["grasps"] == bodies[0]["grasps"] for b in bodies)


def test_a_session_deleted_while_it_is_planned_answers_404(slow_planner):
    sid = _session(slow_planner.url)
    answer: list[httpx.Response] = []
    asking = threading.Thread(target=lambda: answer.append(httpx.get(
        f"{slow_planner.url}/grasp", params={"session_id": sid, "n_candidates": 512},
        timeout=300)))
    asking.start()
    time.sleep(1.0)  # the plan of 512 autograsps is under way
    assert httpx.delete(f"{slow_planner.url}/sessions/{sid}", timeout=60).status_code == 204
    asking.join()
    assert answer[0].status_code == 404, answer[0].text


def test_a_query_parameter_given_twice_is_refused(client):
    """``?session_id=A&session_id=B`` would plan for B silently: 400 naming the parameter."""
    r = client.get("/grasp?session_id=a&session_id=b&top_k=1")
    assert r.status_code == 400 and "session_id" in r.json()["detail"], r.text
    r = client.get("/sessions/x/mesh?format=ply&format=obj")
    assert r.status_code == 400 and "format" in r.json()["detail"]
    assert client.get("/grasp?session_id=nobody&top_k=1").status_code == 404  # once: as before


def test_a_422_lists_at_most_twenty_errors_and_counts_the_rest(client):
    """A body of 50,000 empty points got one error each (a 331 MB answer for 8.4 MB); now the
    points' validation stops at the first bad one, and any 422 lists the first 20 errors and a
    count of the rest (50,000 unknown keys), a few kilobytes."""
    from service.intake.parsing import MAX_ERRORS

    r = client.post("/views", json={"points": [[0.0, 0.0, 0.5]] * 3 + [[]] * 1_900})
    assert r.status_code == 422  # (GRASP_MAX_POINTS is 2,000 here)
    [error] = r.json()["detail"]
    assert error["loc"] == ["body", "points", 3] and error["type"] == "too_short"
    r = client.post("/views", json={"points": [[]] * 50_000})  # refused before it is parsed
    [error] = r.json()["detail"]
    assert r.status_code == 422 and error["loc"] == ["body", "points"]
    assert "holds 50001 JSON arrays" in error["msg"] and "at most 2000 points" in error["msg"]
    r = client.post("/views", json={f"k{i}": 0 for i in range(50_000)} | points_view())
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert len(detail) == MAX_ERRORS + 1 and len(r.content) < 64 * 1024
    assert detail[-1]["type"] == "too_many_errors" and "more errors" in detail[-1]["msg"]
    assert all(e["type"] == "extra_forbidden" for e in detail[:-1])


def test_a_killed_server_leaves_no_process_and_its_pools_start_with_it(tmp_path, tiny_model):
    """Both worker pools (planners, big-body decoders) are running when /healthz first answers;
    after kill -9 of the server none of its processes is left 5 s later (they watch their
    parent: service/intake/workers.py)."""
    server = Server(tmp_path, tiny_model, tmp_path / "store.sqlite", planning_workers=2)
    try:
        family = _descendants(server.process.pid)
        spawned = [pid for pid, command in family.items() if "multiprocessing" in command]
        assert len(spawned) >= 2 + 2, family  # 2 planners + 2 decoders (and the tracker)
    finally:
        server.kill()
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and _alive(family):
        time.sleep(0.1)
    assert not _alive(family), _alive(family)


def _descendants(root: int) -> dict[int, str]:
    """pid -> command line of every process below ``root`` (ps)."""
    table = subprocess.run(["ps", "-eo", "pid=,ppid=,args="], capture_output=True, text=True,
                           check=True).stdout.splitlines()
    rows = [line.split(None, 2) for line in table if line.strip()]
    children: dict[int, list[tuple[int, str]]] = {}
    for pid, ppid, *command in rows:
        children.setdefault(int(ppid), []).append((int(pid), command[0] if command else ""))
    out, todo = {}, [root]
    while todo:
        for pid, command in children.get(todo.pop(), []):
            out[pid] = command
            todo.append(pid)
    return out


def _alive(pids) -> list[int]:
    """Those of ``pids`` that still run (not zombies)."""
    states = subprocess.run(["ps", "-o", "pid=,stat=", "-p", ",".join(map(str, pids))],
                            capture_output=True, text=True).stdout.split()
    return [int(p) for p, st in zip(states[::2], states[1::2], strict=True) if "Z" not in st]
