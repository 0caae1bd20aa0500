"""grasp_client.wire: one definition of what travels, used by the client and the service alike:
its PNG writer against Pillow's reader, the mask rule, the support plane's parsing and checks,
rigid poses, and a grasp through the service's schema and back through the client's reader."""

from __future__ import annotations

import base64
import io

import numpy as np
import pytest
from PIL import Image
from pydantic import TypeAdapter

from grasp_client import wire
from grasp_client.wire import Contact, Grasp, Primitive, SupportPlane
from service.api.schemas import GraspsOut, ViewIn
from service.app import create_app


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("shape", [(1, 1), (3, 7), (48, 64), (240, 320)])
def test_png_writer_round_trips_through_pillow(dtype, shape):
    rng = np.random.default_rng(shape[0] * shape[1])
    image = rng.integers(0, np.iinfo(dtype).max, size=shape, endpoint=True).astype(dtype)
    image[0, 0] = np.iinfo(dtype).max  # the largest value survives the byte-wise "Up" filter
    decoded = np.array(Image.open(io.BytesIO(wire.png_bytes(image)), formats=["PNG"]))
    assert decoded.dtype.itemsize == image.dtype.itemsize
    np.testing.assert_array_equal(decoded.astype(dtype), image)


def test_png_writer_refuses_what_a_depth_png_cannot_hold():
    for bad in (np.zeros((4, 4), np.float32), np.zeros((4, 4, 3), np.uint8), np.zeros((0, 4),
                                                                                         np.uint8)):
        with pytest.raises(ValueError, match="uint8 or uint16"):
            wire.png_bytes(bad)


def test_depth_fields_decode_to_the_same_metres():
    depth = np.array([[0.0, 0.5004], [1.25, np.nan]])
    png = wire.depth_png16_mm(depth)
    mm = np.array(Image.open(io.BytesIO(base64.b64decode(png["data"]))))
    np.testing.assert_array_equal(mm, [[0, 500], [1250, 0]])
    f32 = wire.depth_f32_m(depth)
    back = np.frombuffer(base64.b64decode(f32["data"]), "<f4").reshape(2, 2)
    np.testing.assert_allclose(back, depth.astype(np.float32), equal_nan=True)
    assert (png["width"], png["height"], f32["encoding"]) == (2, 2, "f32_m")


@pytest.mark.parametrize("mask, label, expected", [
    (np.array([[0, 1], [1, 0]], np.uint8), None, [[0, 1], [1, 0]]),
    (np.array([[0, 255], [0, 0]], np.uint8), None, [[0, 1], [0, 0]]),
    (np.array([[False, True], [True, True]]), None, [[0, 1], [1, 1]]),
    (np.array([[0.0, 1.0], [0.0, 0.0]]), None, [[0, 1], [0, 0]]),
    (np.zeros((2, 2), np.uint8), None, [[0, 0], [0, 0]]),
    (np.array([[3, 7], [7, 0]], np.uint16), 7, [[0, 1], [1, 0]]),
])
def test_the_mask_rule(mask, label, expected):
    np.testing.assert_array_equal(wire.object_pixels(mask, label), np.asarray(expected, bool))


@pytest.mark.parametrize("mask", [np.array([[0, 1], [255, 0]], np.uint8),
                                  np.array([[0, 3], [3, 0]], np.uint8),
                                  np.array([[0, 1], [2, 3]], np.int32)])
def test_a_label_image_without_its_label_is_refused_with_its_values(mask):
    with pytest.raises(ValueError, match=r"distinct values \(0, .*object_label"):
        wire.object_pixels(mask)


def test_support_plane_forms_and_checks():
    plane = SupportPlane.from_values([0, 0, 2, -1])
    np.testing.assert_allclose(plane.as_array(), [0, 0, 1, -0.5])
    np.testing.assert_allclose(SupportPlane.parse("0,0,2,-1").as_array(), plane.as_array())
    for bad in ([0, 0, 0, 1], [0, 0, 1], [0, 0, 1, float("nan")], [True, 0, 1, 0], ["0", 0, 1, 0]):
        with pytest.raises(ValueError):
            SupportPlane.from_values(bad)
    for text in ("0,0,1", "a,b,c,d", "0,0,0,1", "0, 0, 1, 0", "0,0,1,1e999"):
        with pytest.raises(ValueError, match="four numbers nx,ny,nz,d"):
            SupportPlane.parse(text)


def test_rigid_pose():
    pose = np.eye(4)
    pose[:3, 3] = [0.1, 0.2, 0.3]
    np.testing.assert_array_equal(wire.rigid_pose(pose.tolist()), pose)
    for bad, says in ((np.diag([1.0, 1, -1, 1]), "rigid"), (np.eye(4)[:3], r"shape \(4, 4\)"),
                      (np.eye(4) * 2000.0, "within"), ([[True] * 4] * 4, "numbers only")):
        with pytest.raises(ValueError, match=says):
            wire.rigid_pose(bad)


def _grasp() -> Grasp:
    pose = np.eye(4)
    pose[:3, 3] = [0.01, 0.02, 0.5]
    return Grasp(
        palm_pose=pose, palm_pose_world=None, pregrasp_pose=pose @ np.diag([1.0, 1, 1, 1]),
        pregrasp_pose_world=None, joints_deg={n: float(i) for i, n in enumerate(wire.JOINT_NAMES)},
        dofs_deg=np.array([10.0, 20, 30, 40]), epsilon=0.1, volume=0.2, force_epsilon=0.3,
        palm_contact=True, approach_stop="contact", hold_probability=None,
        contacts=[Contact("f1_dist", np.array([0.0, 0.01, 0.5]), np.array([0.0, 0.0, -1.0]))],
        hand=[Primitive("palm", "box", [0.1, 0.1, 0.05], pose)],
    )


def test_a_grasp_goes_through_the_service_schema_and_back_through_the_client():
    out = GraspsOut(session_id="s", views=1, grasps=[_grasp()], timing_ms={"total": 1.0},
                    support_plane=SupportPlane.from_values([0, 0, 2, -1]))
    body = out.model_dump(mode="json")
    assert body["support_plane"] == [0.0, 0.0, 1.0, -0.5]
    back = Grasp.from_json(body["grasps"][0])
    original = _grasp()
    for name in ("palm_pose", "pregrasp_pose", "dofs_deg"):
        np.testing.assert_array_equal(getattr(back, name), getattr(original, name))
    assert back.joints == original.joints_deg and back.palm_contact is True
    np.testing.assert_array_equal(back.contacts[0].normal, original.contacts[0].normal)
    np.testing.assert_array_equal(back.hand[0].pose, original.hand[0].pose)
    assert back.joint_array.tolist() == list(range(8))


def test_the_openapi_schema_comes_from_the_wire_types():
    schema = create_app().openapi()["components"]["schemas"]
    grasp = schema["Grasp"]["properties"]
    assert grasp["palm_pose"]["maxItems"] == 4 and grasp["palm_pose"]["items"]["maxItems"] == 4
    assert "pre-grasp" in grasp["pregrasp_pose_world"]["anyOf"][0]["description"]
    assert set(grasp["approach_stop"]["enum"]) == {"contact", "limit", "none"}
    view = schema["ViewIn"]["properties"]
    assert view["support_plane"]["anyOf"][0]["minItems"] == 4
    assert "rigid" in view["camera_pose"]["description"]


def test_the_service_refuses_through_the_same_checks():
    adapter = TypeAdapter(ViewIn)
    base = {"points": [[0.0, 0.0, 0.5]]}
    for field, value, says in (("camera_pose", np.diag([2.0, 1, 1, 1]).tolist(), "rigid"),
                               ("support_plane", [0, 0, 0, 1], "non-zero normal")):
        with pytest.raises(ValueError, match=says):
            adapter.validate_python(base | {field: value})
