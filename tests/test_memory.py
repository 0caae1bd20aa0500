"""service.intake.memory: what a view body and its decoding reserve, the byte budgets that make
requests wait (then 503), and, against a real server, rounds of concurrent bombs of each depth
encoding that stay within 200 MB of idle and give the memory back."""

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
from service.intake.memory import (
    DECODE_BYTES_PER_PIXEL,
    ByteBudget,
    decode_cost,
    return_freed_memory,
    text_cost,
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


def ones_bomb() -> bytes:
    """Just under 32 MiB (GRASP_MAX_BODY_BYTES) of ``[0,0,1]``: 4.19 million points, 41 bytes
    of Python objects per byte of text once parsed."""
    return b'{"points": [' + b",".join([b"[0,0,1]"] * 4_194_000) + b"]}"


def empty_bomb() -> bytes:
    """Just under 32 MiB of ``[]``: 11 million points, each an error to pydantic."""
    return b'{"points": [' + b",".join([b"[]"] * 11_184_000) + b"]}"


def few_empty() -> bytes:
    """500,000 ``[]`` (1.5 MB), as many arrays as a view may hold: parsed, one error answered."""
    return b'{"points": [' + b",".join([b"[]"] * 500_000) + b"]}"


def grid_bomb() -> bytes:
    """A full 40³ grid view (8000 bytes of ones)."""
    pose = [[0.005, 0, 0, -0.1], [0, 0.005, 0, -0.1], [0, 0, 0.005, 0.5], [0, 0, 0, 1]]
    return json.dumps({"grid": {"data": b64(np.packbits(np.ones(40**3, bool)).tobytes()),
                                "grid_to_camera": pose}}).encode()


def _body_shapes(n: int) -> dict[str, bytes]:
    rng = np.random.default_rng(0)
    real = rng.normal(scale=0.05, size=(n, 3)) + (0.0, 0.0, 0.6)
    return {
        "realistic": json.dumps({"points": real.tolist()}).encode(),
        "[0,0,1]": b'{"points": [' + b",".join([b"[0,0,1]"] * n) + b"]}",
        "[0.5,0.25,1.5]": b'{"points": [' + b",".join([b"[0.5,0.25,1.5]"] * n) + b"]}",
        "[]": b'{"points": [' + b",".join([b"[]"] * n) + b"]}",
        "[[]]": b'{"points": [' + b",".join([b"[[]]"] * n) + b"]}",
        "[1e999,0,0]": b'{"points": [' + b",".join([b"[1e999,0,0]"] * n) + b"]}",
        "flat numbers": b'{"points": [' + b",".join([b"0"] * (3 * n)) + b"]}",
    }


@pytest.mark.parametrize("shape", list(_body_shapes(1)))
def test_what_a_body_of_points_reserves_covers_what_parsing_it_holds(shape):
    """The decoding budget's estimate of a JSON body (service.intake.memory.text_cost), measured
    against tracemalloc's peak while the body is parsed, validated and decoded, shape by shape:
    the 40× of ``[0,0,1]`` included."""
    import gc
    import tracemalloc

    from service.intake.parsing import parse_view
    from service.settings import Settings

    raw = _body_shapes(20_000)[shape]
    gc.collect()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        limits = Settings(max_image_pixels=1 << 20, max_points=1 << 20).decode_limits()
        answer = parse_view(raw, "application/json", limits)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert answer[0] == ("ok" if shape in ("realistic", "[0,0,1]", "[0.5,0.25,1.5]") else "error")
    if answer[0] == "error":  # validation stopped at the first bad point
        assert len(answer[2]) == 1 and answer[2][0]["loc"][:3] == ["body", "points", 0], answer
    assert peak <= text_cost(raw), f"{shape}: {peak} B held, {text_cost(raw)} reserved"
    assert peak >= text_cost(raw) / 20, f"{shape}: the estimate is far too high"


def test_a_body_with_more_arrays_than_points_allowed_is_refused_unparsed():
    from service.intake.memory import OTHER_ARRAYS, too_many_arrays

    assert too_many_arrays(b'{"points": [' + b",".join([b"[0,0,1]"] * 10) + b"]}", 10) is None
    view = json.dumps(points_view(n=10) | {"camera_pose": np.eye(4).tolist(),
                                           "support_plane": [0, 0, 1, 0]}).encode()
    assert too_many_arrays(view, 10) is None
    over = b'{"points": [' + b",".join([b"[]"] * (10 + OTHER_ARRAYS)) + b"]}"
    problem = too_many_arrays(over, 10)
    assert problem is not None and f"holds {11 + OTHER_ARRAYS} JSON arrays" in problem
    assert "at most 10 points (GRASP_MAX_POINTS)" in problem


def test_the_decoding_reserves_the_pixels_a_body_declares_however_small_it_is():
    bomb = json.dumps(png_bomb()).encode()
    assert len(bomb) < 64_000
    assert decode_cost(bomb, SIDE * SIDE) == DECODE_BYTES_PER_PIXEL * SIDE * SIDE + len(bomb)
    assert decode_cost(bomb, 1000) == max(DECODE_BYTES_PER_PIXEL * 1000, text_cost(bomb)) \
        + len(bomb)  # refused later
    escaped = bomb.replace(b'"width"', b'"\\u0077idth"')  # the same key to a JSON reader
    assert decode_cost(escaped, 5 * SIDE * SIDE) == DECODE_BYTES_PER_PIXEL * 5 * SIDE * SIDE \
        + len(escaped)
    points = json.dumps(points_view(n=1000)).encode()
    assert decode_cost(points, SIDE * SIDE) == text_cost(points) + len(points)


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


#: Each kind of bomb and the status every one of its views is answered with.
BOMBS = [(png_bomb, 200), (f32_bomb, 200), (ones_bomb, 422), (empty_bomb, 422), (few_empty, 422),
         (grid_bomb, 200)]


@pytest.mark.slow
@pytest.mark.parametrize(("make", "expected"), BOMBS, ids=[m.__name__ for m, _ in BOMBS])
def test_rounds_of_eight_bombs_stay_within_200_mb_of_idle_and_give_it_back(server, make,
                                                                            expected):
    """3 rounds × 8 concurrent bombs: the server and its decoding processes grow by at most
    200 MB over idle, and are back within 50 MB of idle 10 s after each round; every answer is
    at most 64 kB. The first kind's first round meets a server that has answered nothing but
    /healthz (its pools start before that answers)."""
    body = make()
    body = body if isinstance(body, bytes) else json.dumps(body).encode()
    for round_ in range(3):
        idle, peak, after, answers = _round(server, body)
        print(f"{make.__name__} round {round_}: idle {idle:.0f} MB, peak +{peak - idle:.0f},"
              f" after +{after - idle:.0f}, largest answer {max(n for _, n in answers)} B")
        assert [code for code, _ in answers] == [expected] * 8
        assert max(n for _, n in answers) <= 64_000
        assert peak - idle <= 200, f"round {round_}: idle {idle:.0f}, peak {peak:.0f}"
        assert after - idle <= 50, f"round {round_}: idle {idle:.0f}, 10 s after {after:.0f}"


def _round(server: Server, body: bytes) -> tuple[float, float, float, list[tuple[int, int]]]:
    """8 bodies at once: the tree's RSS before, at its peak and once back (10 s at most)."""
    pid = server.process.pid
    time.sleep(1.0)
    idle = _tree_mb(pid)
    peak, done = [idle], threading.Event()

    def watch() -> None:
        while not done.is_set():
            peak.append(_tree_mb(pid))
            time.sleep(0.01)

    answers: list[tuple[int, int]] = []  # status, bytes

    def send() -> None:
        with httpx.Client(base_url=server.url, timeout=300) as c:
            r = c.post("/views", content=body, headers={"content-type": "application/json"})
            answers.append((r.status_code, len(r.content)))

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
