"""service.memory: what a view body and its decoding reserve, the byte budgets that make requests
wait (then 503), and, against a real server, rounds of concurrent bombs of each depth encoding
that stay within 200 MB of idle and give the memory back."""

from __future__ import annotations

import asyncio
import json
import subprocess
import threading
import time

import httpx
import numpy as np
import pytest
from fastapi import HTTPException
from service_helpers import Server, points_view

from grasp_client.wire import b64, png_bytes
from service.memory import (
    DECODE_BYTES_PER_PIXEL,
    TEXT_EXPANSION,
    ByteBudget,
    decode_cost,
    return_freed_memory,
)

MB = 1e6
SIDE = 2048
K = {"fx": 1800.0, "fy": 1800.0, "cx": 1023.5, "cy": 1023.5}


def png_bomb() -> dict:
    """About 29 kB of body: a constant 2048² 16-bit depth PNG and an all-object mask, within
    GRASP_MAX_IMAGE_PIXELS, that back-projects to 4,194,304 points (thinned to the cap)."""
    depth = np.full((SIDE, SIDE), 600, np.uint16)
    return {"depth": {"encoding": "png16_mm", "width": SIDE, "height": SIDE,
                      "data": b64(png_bytes(depth))}, "intrinsics": K,
            "mask": b64(png_bytes(np.full((SIDE, SIDE), 255, np.uint8)))}


def f32_bomb() -> dict:
    """22 MB of body: 2048² float32 metres with an all-object mask."""
    depth = np.full((SIDE, SIDE), 0.6, "<f4")
    return {"depth": {"encoding": "f32_m", "width": SIDE, "height": SIDE,
                      "data": b64(depth.tobytes())}, "intrinsics": K,
            "mask": b64(png_bytes(np.full((SIDE, SIDE), 255, np.uint8)))}


def test_the_decoding_reserves_the_pixels_a_body_declares_however_small_it_is():
    bomb = json.dumps(png_bomb()).encode()
    assert len(bomb) < 64_000
    assert decode_cost(bomb, SIDE * SIDE) == DECODE_BYTES_PER_PIXEL * SIDE * SIDE + len(bomb)
    assert decode_cost(bomb, 1000) == TEXT_EXPANSION * len(bomb) + len(bomb)  # refused later
    escaped = bomb.replace(b'"width"', b'"\\u0077idth"')  # the same key to a JSON reader
    assert decode_cost(escaped, 5 * SIDE * SIDE) == DECODE_BYTES_PER_PIXEL * 5 * SIDE * SIDE \
        + len(escaped)
    points = json.dumps(points_view(n=1000)).encode()
    assert decode_cost(points, SIDE * SIDE) == (TEXT_EXPANSION + 1) * len(points)


def test_a_budget_makes_requests_wait_then_answers_503_and_lets_a_big_one_run_alone():
    async def scenario() -> list[str]:
        budget = ByteBudget("views", 100, wait_s=0.3)
        order: list[str] = []

        async def request(name: str, n: int, hold_s: float) -> None:
            try:
                async with budget.hold(n):
                    order.append(f"{name} in")
                    await asyncio.sleep(hold_s)
                order.append(f"{name} out")
            except HTTPException as exc:
                assert exc.status_code == 503 and exc.headers == {"Retry-After": "1"}
                assert "a budget of 100 bytes" in exc.detail
                order.append(f"{name} 503")

        await asyncio.gather(request("a", 60, 0.1), request("b", 60, 0.1),
                             request("c", 500, 0.05), request("d", 60, 1.0))
        assert budget.free == 100
        return order

    order = asyncio.run(scenario())
    assert order[:2] == ["a in", "a out"] and order.index("b in") > order.index("a out")
    assert "c in" in order  # bigger than the budget: it ran, alone
    assert "d 503" in order or order.index("d in") > order.index("c out")


def test_freed_arrays_go_back_to_the_system():
    assert return_freed_memory()  # glibc here


def _rss_mb(pid: int) -> float:
    for line in open(f"/proc/{pid}/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def _tree_mb(pid: int) -> float:
    """The server's RSS and its children's (the processes that decode big bodies)."""
    children = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True,
                              text=True).stdout.split()
    total = _rss_mb(pid)
    for child in children:
        try:
            total += _tree_mb(int(child))
        except (FileNotFoundError, AssertionError):
            pass  # gone meanwhile
    return total


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("memory")
    s = Server(tmp, "mvp", tmp / "store.sqlite")  # the shipped model, as deployed
    yield s
    s.stop()


@pytest.mark.slow
@pytest.mark.parametrize("make", [png_bomb, f32_bomb])
def test_rounds_of_eight_bombs_stay_within_200_mb_of_idle_and_give_it_back(server, make):
    """3 rounds × 8 concurrent bombs: the server and its decoding processes grow by at most
    200 MB over idle, and are back within 50 MB of idle 10 s after each round."""
    body = json.dumps(make()).encode()
    with httpx.Client(base_url=server.url, timeout=300) as client:  # warm: the pool is up
        assert client.post("/views", json=points_view()).status_code == 200
        assert client.post("/views", content=body,
                           headers={"content-type": "application/json"}).status_code == 200
    for round_ in range(3):
        idle, peak, after, answers = _round(server, body)
        print(f"{make.__name__} round {round_}: idle {idle:.0f} MB, peak +{peak - idle:.0f},"
              f" after +{after - idle:.0f}")
        assert answers == [200] * 8
        assert peak - idle <= 200, f"round {round_}: idle {idle:.0f}, peak {peak:.0f}"
        assert after - idle <= 50, f"round {round_}: idle {idle:.0f}, 10 s after {after:.0f}"


def _round(server: Server, body: bytes) -> tuple[float, float, float, list[int]]:
    """8 bodies at once: the tree's RSS before, at its peak and once back (10 s at most)."""
    pid = server.process.pid
    time.sleep(1.0)
    idle = _tree_mb(pid)
    peak, done = [idle], threading.Event()

    def watch() -> None:
        while not done.is_set():
            peak.append(_tree_mb(pid))
            time.sleep(0.01)

    answers: list[int] = []

    def send() -> None:
        with httpx.Client(base_url=server.url, timeout=300) as c:
            answers.append(c.post("/views", content=body,
                                  headers={"content-type": "application/json"}).status_code)

    watcher = threading.Thread(target=watch)
    watcher.start()
    senders = [threading.Thread(target=send) for _ in range(8)]
    for t in senders:
        t.start()
    for t in senders:
        t.join()
    done.set()
    watcher.join()
    deadline = time.monotonic() + 10.0
    while (after := _tree_mb(pid)) - idle > 50 and time.monotonic() < deadline:
        time.sleep(0.5)
    return idle, max(peak), after, answers
