"""Hostile bodies against a real ``python -m service``: deep nesting, a depth image that
back-projects to millions of points, numbers and encodings JSON readers disagree on. Each answer
is a 4xx that says what was expected, and the server's memory stays bounded."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from service_helpers import Server, points_view

from grasp_client.wire import b64, png_bytes


@pytest.fixture(scope="module")
def server(tmp_path_factory, tiny_model):
    tmp = tmp_path_factory.mktemp("hostile")
    s = Server(tmp, tiny_model, tmp / "store.sqlite")
    yield s
    s.stop()


def _post(client: httpx.Client, content: bytes, **headers) -> httpx.Response:
    return client.post("/views", content=content,
                       headers={"content-type": "application/json"} | headers)


def test_deep_nesting_is_a_400_that_says_so_and_the_connection_lives_on(server):
    with httpx.Client(base_url=server.url, timeout=60) as client:
        for body in (b"[" * 100_000,  # parsed in a thread
                     b'{"points":' + b"[" * 2000 + b"]" * 2000 + b"}",
                     b"[" * 600_000):  # over 512 kB: parsed in a worker process
            r = _post(client, body)
            assert r.status_code == 400, (len(body), r.text)
            assert "nested too deeply" in r.json()["detail"]
            ok = client.post("/views", json=points_view())  # the same connection still works
            assert ok.status_code == 200


def test_numbers_and_encodings_get_messages_that_name_the_problem(server):
    with httpx.Client(base_url=server.url, timeout=60) as client:
        r = _post(client, b'{"points": [[1, 2, ' + b"9" * 5000 + b"]]}")
        assert r.status_code == 400 and "4300 digits" in r.json()["detail"]
        utf16 = '{"points": [[0, 0, 0.5], [0.01, 0, 0.5], [0, 0.01, 0.5]]}'.encode("utf-16")
        r = _post(client, utf16)
        assert r.status_code == 400 and "not UTF-8" in r.json()["detail"]
        sid = client.post("/views", json=points_view()).json()["session_id"]
        r = client.get("/grasp", params={"session_id": sid, "support_plane": "0,0,1,1e999"})
        assert r.status_code == 422
        message = r.json()["detail"][0]["msg"]
        assert "exponents of at most two digits" in message and "normal" not in message.split(
            ";")[0].split("(")[0]
        page = client.get("/sessions/no-such-session/view")  # never says whether one exists
        assert page.status_code == 200 and page.text == client.get(f"/sessions/{sid}/view").text


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def _png_bomb() -> dict:
    """29 kB of JSON: a constant 2048 × 2048 16-bit depth PNG and an all-object mask, within
    GRASP_MAX_IMAGE_PIXELS, that back-projects to 4,194,304 points."""
    depth = np.full((2048, 2048), 500, np.uint16)
    mask = np.full((2048, 2048), 255, np.uint8)
    return {"depth": {"encoding": "png16_mm", "width": 2048, "height": 2048,
                      "data": b64(png_bytes(depth))},
            "intrinsics": {"fx": 1500.0, "fy": 1500.0, "cx": 1023.5, "cy": 1023.5},
            "mask": b64(png_bytes(mask))}


@pytest.mark.slow
def test_eight_png_bombs_at_once_stay_within_200_mb_of_idle(server):
    bomb = _png_bomb()
    assert len(httpx.Request("POST", "http://x", json=bomb).content) < 64 * 1024
    with httpx.Client(base_url=server.url, timeout=120) as client:
        assert client.post("/views", json=points_view()).status_code == 200  # warm
        assert client.post("/views", json=bomb).status_code == 200  # thinned, not refused
    time.sleep(0.5)
    pid = server.process.pid
    idle = _rss_mb(pid)
    peak, done = [idle], threading.Event()

    def watch() -> None:
        while not done.is_set():
            peak.append(_rss_mb(pid))
            time.sleep(0.01)

    answers: list[int] = []

    def send() -> None:
        with httpx.Client(base_url=server.url, timeout=300) as client:
            answers.append(client.post("/views", json=bomb).status_code)

    watcher = threading.Thread(target=watch)
    watcher.start()
    senders = [threading.Thread(target=send) for _ in range(8)]
    for t in senders:
        t.start()
    for t in senders:
        t.join()
    done.set()
    watcher.join()
    assert answers == [200] * 8
    print(f"RSS idle {idle:.0f} MB, peak under 8 bombs {max(peak):.0f} MB")
    assert max(peak) - idle < 200, f"idle {idle:.0f} MB, peak {max(peak):.0f} MB"
