"""Bad input and error answers: every rejected view leaves the session untouched (422), and
413, 409, 400 say what was expected. Through FastAPI's TestClient with a tiny model."""

from __future__ import annotations

import base64
import io
import json

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient
from service_helpers import (
    MAX_BODY,
    MAX_POINTS,
    TINY,
    hidden_view,
    new_session,
    occupancy,
    points_view,
    settings,
    stored_state,
)

from completion.grid import VoxelGrid
from completion.model import build_model, save_checkpoint
from grasp_client.wire import b64, depth_f32_m, grid_field, mask_png, png_bytes
from service.app import create_app
from service.load import scene_views

# --------------------------------------------------------------------------------- bad input


def _png16(h=240, w=320) -> str:
    return b64(png_bytes(np.full((h, w), 500, np.uint16)))


def _png8() -> str:
    return b64(png_bytes(np.zeros((240, 320), np.uint8)))


EYE = np.eye(4).tolist()


def _z_shift(z: float) -> np.ndarray:
    shift = np.zeros((4, 4))
    shift[2, 3] = z
    return shift


def _depth_view(scene, **depth) -> dict:
    body = scene_views(scene, with_pose=False)[0]
    body["depth"] = body["depth"] | depth
    return body


# (name, body maker, loc, message); each is rejected with 422 and leaves the session untouched.
BAD_VIEWS = [
    ("nan point", lambda s: '{"points": [[0, 0, NaN]]}', ["body", "points", 0, 2], "finite number"),
    ("inf point", lambda s: '{"points": [[0, Infinity, 1]]}', ["body", "points", 0, 1], "finite"),
    ("point behind", lambda s: {"points": [[0, 0, 0.5], [0, 0, -0.1]]}, ["body", "points"],
     "in front of the camera (z > 0 m, camera frame); point 1 has z = -0.1"),
    ("far point", lambda s: {"points": [[0, 0, 5e3]]}, ["body", "points"], "within ±1000 m"),
    ("short point", lambda s: {"points": [[0, 0]]}, ["body", "points", 0], "at least 3 items"),
    ("long point", lambda s: {"points": [[0, 0, 1, 2]]}, ["body", "points", 0], "at most 3 items"),
    ("too many points", lambda s: points_view(MAX_POINTS + 1), ["body", "points"],
     f"at most {MAX_POINTS} points per view, got {MAX_POINTS + 1}"),
    ("points and depth", lambda s: _depth_view(s) | points_view(), ["body"],
     "give exactly one of points, depth (with intrinsics) or grid; got points and depth"),
    ("nothing", lambda s: {"camera_pose": np.eye(4).tolist()}, ["body"], "got none"),
    ("depth without intrinsics", lambda s: {"depth": _depth_view(s)["depth"]}, ["body"],
     "depth needs intrinsics"),
    ("mask without depth", lambda s: points_view() | {"mask": _depth_view(s)["mask"]}, ["body"],
     "intrinsics, mask and obstacle_mask go with depth only"),
    ("depth not base64", lambda s: _depth_view(s, data="@@@"), ["body", "depth", "data"],
     "depth.data must be standard base64"),
    ("depth not png", lambda s: _depth_view(s, data=b64(b"GIF89a" + bytes(20))),
     ["body", "depth", "data"], "depth.data is not a PNG image"),
    ("truncated png", lambda s: _depth_view(s, data=b64(base64.b64decode(_png16())[:60])),
     ["body", "depth", "data"], "depth.data"),
    ("8-bit depth png", lambda s: _depth_view(s, data=_png8()), ["body", "depth", "data"],
     "must be a 16-bit single-channel PNG (mm), got PNG mode L"),
    ("depth png size", lambda s: _depth_view(s, data=_png16(120, 160)), ["body", "depth", "data"],
     "depth PNG is 160×120 but width × height say 320×240"),
    ("f32 length", lambda s: _depth_view(s, encoding="f32_m", data=b64(bytes(12))),
     ["body", "depth", "data"], "needs width × height × 4 = 307200 bytes, got 12"),
    ("f32 negative", lambda s: _depth_view(s, **depth_f32_m(-np.ones((240, 320))),),
     ["body", "depth", "data"], "depth must be ≥ 0 m"),
    ("unknown encoding", lambda s: _depth_view(s, encoding="png8"), ["body", "depth", "encoding"],
     "Input should be 'png16_mm' or 'f32_m'"),
    ("image too large", lambda s: _depth_view(s, width=321), ["body", "depth"],
     "image is 321×240 = 77040 pixels; the limit is 76800 pixels"),
    ("zero width", lambda s: _depth_view(s, width=0), ["body", "depth", "width"],
     "greater than 0"),
    ("mask size", lambda s: _depth_view(s) | {"mask": mask_png(np.ones((120, 160)))},
     ["body", "mask"], "mask is 160×120 but the depth image is 320×240"),
    ("mask rgb", lambda s: _depth_view(s) | {"mask": _rgb_png()}, ["body", "mask"],
     "mask must be an 8-bit single-channel PNG, got PNG mode RGB"),
    ("mask not base64", lambda s: _depth_view(s) | {"mask": "a"}, ["body", "mask"],
     "mask must be standard base64"),
    ("fx zero", lambda s: _depth_view(s) | {"intrinsics": {"fx": 0, "fy": 1, "cx": 0, "cy": 0}},
     ["body", "intrinsics", "fx"], "greater than 0"),
    ("boolean coordinate", lambda s: {"points": [[0, 0, True]]}, ["body", "points", 0, 2],
     "valid number"),  # strict: true is not 1 m
    ("string coordinate", lambda s: {"points": [[0, "0", 0.5]]}, ["body", "points", 0, 1],
     "valid number"),
    ("grid behind", lambda s: {"grid": {"data": b64(bytes(8000)), "grid_to_camera": (
        np.diag([0.005, 0.005, 0.005, 1.0]) + _z_shift(-5.0)).tolist()}},
     ["body", "grid", "grid_to_camera"], "the grid lies behind the camera"),
    ("grid length", lambda s: {"grid": {"data": b64(bytes(10)), "grid_to_camera": EYE}},
     ["body", "grid", "data"], "grid.data must hold 8000 bytes (40³ bits packed"),
    ("grid singular", lambda s: {"grid": {"data": b64(bytes(8000)),
                                          "grid_to_camera": np.diag([1.0, 1, 0, 1]).tolist()}},
     ["body", "grid", "grid_to_camera"], "pitch × identity plus a translation"),
    ("grid rotated", lambda s: {"grid": {"data": b64(bytes(8000)),
                                         "grid_to_camera": np.eye(4)[[1, 0, 2, 3]].tolist()}},
     ["body", "grid", "grid_to_camera"], "grid axes along the camera axes"),
    ("intrinsics not pixels", lambda s: _depth_view(s) | {"intrinsics": {
        "fx": 1e-9, "fy": 1e-9, "cx": 0, "cy": 0}}, ["body", "intrinsics"],
     "focal lengths are in pixels"),
    ("pose not rigid", lambda s: points_view() | {"camera_pose": np.diag([2.0, 1, 1, 1]).tolist()},
     ["body", "camera_pose"], "rigid camera→world transform"),
    ("pose last row", lambda s: points_view() | {"camera_pose": np.ones((4, 4)).tolist()},
     ["body", "camera_pose"], "last row [0, 0, 0, 1]"),
    ("pose 3×4", lambda s: points_view() | {"camera_pose": np.eye(4)[:3].tolist()},
     ["body", "camera_pose"], "must have shape (4, 4)"),
    ("unknown field", lambda s: points_view() | {"camera_to_world": 1}, ["body", "camera_to_world"],
     "Extra inputs are not permitted"),
    ("not json", lambda s: '{"points": [[0, 0, 1]', None, "JSON decode error"),
]  # fmt: skip


def _rgb_png() -> str:
    from PIL import Image

    buffer = io.BytesIO()
    Image.new("RGB", (320, 240)).save(buffer, format="PNG")
    return b64(buffer.getvalue())


@pytest.mark.parametrize("name, make, loc, message", BAD_VIEWS, ids=[c[0] for c in BAD_VIEWS])
@pytest.mark.parametrize("existing", [False, True], ids=["new", "existing"])
def test_bad_view_is_rejected_and_changes_nothing(
    client, scene, name, make, loc, message, existing
):
    sid = new_session(client) if existing else None
    before = client.get(f"/sessions/{sid}").json() if existing else None
    state = stored_state(client.app.state.settings.store_path, sid) if existing else None
    body = make(scene)
    if isinstance(body, dict):
        raw = json.dumps(body | ({"session_id": sid} if existing else {}))
    else:  # raw JSON text (NaN, broken JSON): session_id goes first
        raw = body if not existing else body.replace("{", f'{{"session_id": "{sid}", ', 1)
        loc = loc or ["body", len(raw)]  # broken JSON: where the text ends
    r = client.post("/views", content=raw, headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    [error] = [e for e in r.json()["detail"] if e["loc"] == loc] or r.json()["detail"][:1]
    assert error["loc"] == loc and message in error["msg"], r.json()
    assert "input" not in error  # the body is not echoed back
    if existing:
        assert client.get(f"/sessions/{sid}").json() == before
        assert stored_state(client.app.state.settings.store_path, sid) == state
    assert client.get("/healthz").json()["sessions"] == int(existing)


def test_body_over_the_limit_is_413(client):
    sid = new_session(client)
    big = json.dumps(points_view() | {"session_id": sid, "pad": "x" * MAX_BODY})
    r = client.post("/views", content=big, headers={"content-type": "application/json"})
    assert r.status_code == 413
    limit = f"request body over the limit of {MAX_BODY} bytes (GRASP_MAX_BODY_BYTES)"
    assert r.json()["detail"] == limit

    def chunks():  # no Content-Length: counted while it streams
        data = big.encode()
        for i in range(0, len(data), 65536):
            yield data[i : i + 65536]

    r = client.post("/views", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413 and "over the limit" in r.json()["detail"]
    assert client.get(f"/sessions/{sid}").json()["views"] == 1


def test_no_object_yet_is_409(client):
    r = client.post("/views", json={"points": []})  # no points at all: a mistake, said
    assert r.status_code == 422 and "points is empty" in r.text
    r = client.post("/views", json=hidden_view())  # a fully occluded view: an empty mask
    assert r.status_code == 200 and r.json()["observed_voxels"] == 0
    sid = r.json()["session_id"]
    assert client.get(f"/sessions/{sid}").json()["object_seen"] is False
    for path, params in [
        ("/grasp", {"session_id": sid}),
        (f"/sessions/{sid}/mesh", {}),
        (f"/sessions/{sid}/occupancy", {}),
    ]:
        r = client.get(path, params=params)
        assert r.status_code == 409, r.text
        assert r.json()["detail"] == (
            "no view with object points has been added yet; "
            "POST /views with a view that shows the object first"
        )
    assert client.post("/views", json=points_view() | {"session_id": sid}).json()["view_index"] == 1
    assert client.get(f"/sessions/{sid}/occupancy").status_code == 200


def test_all_zero_grid_session_is_409(client, scene):
    """A grid view with no occupied voxel is no sighting: 0 occupied voxels, then 409."""
    empty = VoxelGrid(np.zeros_like(scene.inputs[0]), scene.grid_to_camera[0])
    r = client.post("/views", json={"grid": grid_field(empty)})
    assert r.status_code == 200 and r.json()["occupied_voxels"] == 0, r.text
    sid = r.json()["session_id"]
    assert client.get(f"/sessions/{sid}").json()["object_seen"] is False
    assert client.get("/grasp", params={"session_id": sid}).status_code == 409


def test_occluded_view_after_a_camera_move_stays_on_the_object(client, scene):
    """Camera moved 1 m, then a view with no object points: the grid stays where the object
    is in the world (re-expressed in the new camera frame), so world poses stay on it."""
    first = scene_views(scene)[0]
    sid = new_session(client, first)
    _, before = occupancy(client, sid)
    moved = np.asarray(first["camera_pose"]) @ _translation([1.0, 0.0, 0.0])
    r = client.post("/views", json=hidden_view() | {"camera_pose": moved.tolist(),
                                                     "session_id": sid})
    assert r.status_code == 200 and r.json()["observed_voxels"] == 0, r.text
    _, after = occupancy(client, sid)
    centre = np.array([19.5, 19.5, 19.5, 1.0])
    world_before = np.asarray(first["camera_pose"]) @ np.asarray(before["grid_to_camera"]) @ centre
    world_after = moved @ np.asarray(after["grid_to_camera"]) @ centre
    np.testing.assert_allclose(world_after, world_before, atol=1e-9)
    r = client.get("/grasp", params={"session_id": sid, "top_k": 1, "n_candidates": 8})
    if r.status_code == 200 and r.json()["grasps"]:  # the tiny model may complete nothing
        palm = np.asarray(r.json()["grasps"][0]["palm_pose_world"])
        assert np.linalg.norm(palm[:3, 3] - world_before[:3]) < 0.3


def _translation(offset) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = offset
    return pose


def test_empty_completion_is_409(tmp_path):
    model = build_model(TINY)
    with torch.no_grad():
        model.decoder.out.bias.fill_(-50.0)  # every voxel empty
    path = tmp_path / "empty.pt"
    save_checkpoint(model, path)
    with TestClient(create_app(settings(tmp_path, str(path)))) as client:
        sid = new_session(client)
        for path_, params in [("/grasp", {"session_id": sid}), (f"/sessions/{sid}/mesh", {})]:
            r = client.get(path_, params=params)
            assert r.status_code == 409
            assert r.json()["detail"] == (
                "no voxel reaches the threshold: the completion is empty; "
                "nothing to mesh or grasp: add views that show the object"
            )
        assert occupancy(client, sid)[1]["occupied_voxels"] == 0


@pytest.mark.parametrize(
    "params, loc, message",
    [
        ({"n_candidates": 17}, ["query", "n_candidates"], "must be at most 16, got 17"),
        ({"n_candidates": 0}, ["query", "n_candidates"], "greater than or equal to 1"),
        ({"top_k": 0}, ["query", "top_k"], "greater than or equal to 1"),
        ({"top_k": "one"}, ["query", "top_k"], "valid integer"),
        ({"session_id": None}, ["query", "session_id"], "Field required"),
    ],
)
def test_bad_grasp_query_is_422(client, params, loc, message):
    sid = new_session(client)
    query = {"session_id": sid} | params
    r = client.get("/grasp", params={k: v for k, v in query.items() if v is not None})
    assert r.status_code == 422
    [error] = r.json()["detail"]
    assert error["loc"] == loc and message in error["msg"]


def test_bad_mesh_format_is_422(client):
    sid = new_session(client)
    r = client.get(f"/sessions/{sid}/mesh", params={"format": "zip"})
    assert r.status_code == 422
    assert "'ply', 'obj', 'stl' or 'glb'" in r.json()["detail"][0]["msg"]


@pytest.mark.parametrize(
    ("body", "content_type", "code"),
    [
        (b"{not json", "application/json", 422),
        (b"\xff\xfe\x00", "application/json", 400),
        (b'{"points": [[0, 0, 1]]}', "text/plain", 422),
        (b"a=1", "application/x-www-form-urlencoded", 422),
    ],
)
def test_unparsable_bodies_say_what_was_expected(client, body, content_type, code):
    r = client.post("/views", content=body, headers={"content-type": content_type})
    assert r.status_code == code
    text = r.text
    assert "one JSON object in UTF-8" in text and "application/json" in text, text
    assert "object at 0x" not in text  # no Python reprs


def test_a_view_resent_with_its_idempotency_key_is_applied_once(client):
    """A client that lost the answer sends the view again with the same key: the first answer
    comes back and the session holds the view once; another key is another view."""
    first = client.post("/views", json=points_view(), headers={"Idempotency-Key": "view-a"})
    again = client.post("/views", json=points_view(), headers={"Idempotency-Key": "view-a"})
    assert first.status_code == again.status_code == 200
    assert again.json() == first.json()
    sid = first.json()["session_id"]
    assert client.get(f"/sessions/{sid}").json()["views"] == 1
    body = points_view(seed=1) | {"session_id": sid}
    for _ in range(2):
        r = client.post("/views", json=body, headers={"Idempotency-Key": "view-b"})
        assert r.status_code == 200 and r.json()["view_index"] == 1
    assert client.get(f"/sessions/{sid}").json()["views"] == 2
    r = client.post("/views", json=points_view(), headers={"Idempotency-Key": "bad key"})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["header", "idempotency-key"]
