"""The mistakes a robot integration makes, caught where they enter: through the real client
against a real ``python -m service``, and as raw HTTP. Each error names the field and the fix."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from service_helpers import Server

from grasp_client import GraspClient, InvalidRequest, NothingSeen
from grasp_client.wire import b64, depth_f32_m, png_bytes


@pytest.fixture(scope="module")
def server(tmp_path_factory, tiny_model):
    tmp = tmp_path_factory.mktemp("mistakes")
    s = Server(tmp, tiny_model, tmp / "store.sqlite")
    yield s
    s.stop()


@pytest.fixture(scope="module")
def view(scene):
    """The first view of the camera-pan scene: depth (m), the label image, its K."""
    k = scene.meta["intrinsics"]
    K = np.array([[k["fx"], 0, k["cx"]], [0, k["fy"], k["cy"]], [0, 0, 1]])
    return np.nan_to_num(scene.depth[0]).astype(np.float32), scene.mask[0], K


def refused(call, field: str, *words: str) -> InvalidRequest:
    with pytest.raises(InvalidRequest) as err:
        call()
    assert err.value.field == field, (err.value.field, str(err.value))
    for word in words:
        assert word in str(err.value), str(err.value)
    return err.value


def test_a_label_image_as_the_mask(server, view):
    depth, labels, K = view  # labels: -1 background, 0 the object
    with GraspClient(server.url) as client, client.session() as session:
        refused(lambda: session.add_view(depth, K, mask=labels), "mask", "int", "-1, 0",
                "object_label")
        right = session.add_view(depth, K, mask=labels, object_label=0)
        boolean = session.add_view(depth, K, mask=labels >= 0)
        assert right["occupied_voxels"] == boolean["occupied_voxels"] > 100
        refused(lambda: session.add_view(depth, K, object_label=0), "object_label", "mask")
    three = np.where(labels >= 0, 2, 1).astype(np.uint8)  # a PNG label image, raw HTTP
    body = {"depth": depth_f32_m(depth), "intrinsics": _k(K), "mask": b64(png_bytes(three))}
    r = httpx.post(f"{server.url}/views", json=body, timeout=60)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "mask"]
    assert "2 distinct values (1, 2)" in r.text and "object_label" in r.text
    r = httpx.post(f"{server.url}/views", json=body | {"object_label": 2}, timeout=60)
    assert r.status_code == 200, r.text


def test_millimetres_sent_as_metres(server, view):
    depth, labels, K = view
    with GraspClient(server.url) as client, client.session() as session:
        refused(lambda: session.add_view(depth * 1000, K, mask=labels >= 0), "depth.data",
                "GRASP_MAX_DEPTH_MEDIAN_M", "looks like millimetres", "png16_mm")
        points = np.array([[0.0, 0.0, 500.0], [30.0, 0.0, 510.0], [0.0, 30.0, 520.0]])
        refused(lambda: session.add_points(points), "points", "GRASP_MAX_POINT_DISTANCE_M",
                "divide by 1000")
        assert session.id is None  # nothing was stored


def test_implausible_intrinsics(server, view):
    depth, labels, K = view
    swapped = K.copy()
    swapped[0, 2], swapped[1, 2] = K[1, 2], K[0, 2]
    outside = K.copy()
    outside[1, 2] = 2 * K[1, 2] + 40  # below the image
    metres = K.copy()
    metres[0, 0] = metres[1, 1] = 3.08
    with GraspClient(server.url) as client, client.session() as session:
        refused(lambda: session.add_view(depth, swapped, mask=labels >= 0), "intrinsics",
                "cx and cy look swapped")
        refused(lambda: session.add_view(depth, outside, mask=labels >= 0), "intrinsics",
                "lies outside the 320×240 depth image")
        refused(lambda: session.add_view(depth, metres, mask=labels >= 0), "intrinsics",
                "fx = 3.08", "focal lengths are in pixels")
    body = {"depth": depth_f32_m(depth), "intrinsics": K.tolist()}  # 3×3 K as a JSON list
    r = httpx.post(f"{server.url}/views", json=body, timeout=60)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "intrinsics"]
    assert r.text.count("not a list") == 1 and "K[0][0]" in r.text and "content-type" not in r.text


def test_the_client_raises_only_its_documented_errors(server, view):
    depth, labels, K = view
    with GraspClient(server.url) as client, client.session() as session:
        with pytest.raises(NothingSeen, match="no view yet"):
            session.grasps()
        with pytest.raises(NothingSeen, match="no view yet"):
            session.mesh()
        session.add_view(depth, K, mask=np.zeros(depth.shape, bool))  # nothing of the object
        with pytest.raises(NothingSeen, match="409"):
            session.grasps()


def _k(K: np.ndarray) -> dict:
    return {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]),
            "cy": float(K[1, 2])}
