"""Hostile bodies against a real ``python -m service``: deep nesting, a depth image that
back-projects to millions of points, numbers and encodings JSON readers disagree on. Each answer
is a 4xx that says what was expected (rounds of memory bombs: tests/test_memory.py)."""

from __future__ import annotations

import httpx
import pytest
from service_helpers import Server, points_view


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
                     b'{"a":' * 120_000):  # over 512 kB: parsed in a worker process
            r = _post(client, body)
            assert r.status_code == 400, (len(body), r.text)
            assert "nested too deeply" in r.json()["detail"]
            ok = client.post("/views", json=points_view())  # the same connection still works
            assert ok.status_code == 200
        r = _post(client, b"[" * 600_000)  # more arrays than points allowed: never parsed
        assert r.status_code == 422 and "600000 JSON arrays" in r.json()["detail"][0]["msg"]


def test_numbers_and_encodings_get_messages_that_name_the_problem(server):
    with httpx.Client(base_url=server.url, timeout=60) as client:
        r = _post(client, b'{"points": [[1, 2, ' + b"9" * 5000 + b"]]}")
        assert r.status_code == 400 and "4300 digits" in r.json()["detail"]
        assert "(points)" in r.json()["detail"]  # the field it stands under
        r = _post(client, b'{"points": [[0, 0, 0.5]], "object_label": ' + b"9" * 5000 + b"}")
        assert "(object_label)" in r.json()["detail"]
        png = {"depth": {"encoding": "png16_mm", "width": 4, "height": 4,
                         "data": "bm90IGEgcG5n"}, "intrinsics": {"fx": 500, "fy": 500,
                                                                 "cx": 2, "cy": 2}}
        r = client.post("/views", json=png)  # "not a png": no object's repr in the message
        assert r.status_code == 422 and "0x" not in r.text and "BytesIO" not in r.text, r.text
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
