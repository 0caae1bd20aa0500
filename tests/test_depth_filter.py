"""Cleaning a depth camera's input (completion/depth.py): flying pixels go, surfaces and thin parts
stay, a few stray points do not stretch the grid, and the service cleans as the evaluation does."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from completion import grid
from completion.depth import DEPTH_FILTER, DepthFilter
from completion.depth_camera import Renderer, SensorModel

INTRINSICS = grid.DEFAULT_INTRINSICS
FLYING_ONLY = SensorModel(sigma_base=0.0, sigma_quadratic=0.0, edge_hole=0.0, subpixel=0,
                          dropout=0.0)
BOX, HANDLE = 0, 1


def _at(x: float, y: float, z: float) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = (x, y, z)
    return pose


@pytest.fixture(scope="module")
def box_wall():
    """A 10 cm box and a 5 mm thin handle 0.45–0.5 m in front of the camera, a wall at 1 m."""
    with Renderer() as r:
        r.add_mesh(trimesh.creation.box((0.1, 0.1, 0.1)), _at(-0.03, 0.0, 0.5))
        r.add_mesh(trimesh.creation.box((0.005, 0.12, 0.005)), _at(0.06, 0.0, 0.5))
        r.add_mesh(trimesh.creation.box((1.5, 1.5, 0.02)), _at(0.0, 0.0, 1.0))
        return r.render(np.eye(4))


def _supported(depth):
    return DEPTH_FILTER.supported(depth, INTRINSICS.fx, INTRINSICS.fy)


@pytest.mark.parametrize("seed", range(3))
def test_flying_pixels_go_the_box_and_a_thin_handle_stay(box_wall, seed):
    depth, seg = box_wall
    noisy = FLYING_ONLY.apply(depth, np.random.default_rng(seed))
    keep = _supported(noisy)
    behind = noisy - depth
    flying = (seg >= 0) & (seg <= HANDLE) & (behind > 1e-4)
    assert flying.sum() > 30  # the sensor model made some
    # farther behind the rim than any neighbour's tolerance (≤ 13 mm at 0.5 m): every one goes
    far = flying & (behind > 0.015)
    assert far.sum() > 20 and not keep[far].any()
    for index, share in ((BOX, 0.98), (HANDLE, 0.98)):
        own = (seg == index) & ~flying
        assert keep[own].mean() >= share, (index, keep[own].mean())
    # the whole sensor model (noise, holes, quantization, dropout): the box's pixels stay
    full = SensorModel().apply(depth, np.random.default_rng(seed))
    own = (seg == BOX) & (np.abs(full - depth) < 0.005)
    assert _supported(full)[own].mean() >= 0.98


def test_the_table_behind_a_rim_does_not_hold_a_flying_pixel_up():
    """A 2 cm plate 2 cm in front of a wall: flying pixels of its rim fall towards the wall, and
    those that land near it are continuous with the wall's pixels. With the object's mask only
    the object's pixels support, and every one more than 1.5 cm behind the plate goes."""
    with Renderer() as r:
        r.add_mesh(trimesh.creation.box((0.1, 0.1, 0.02)), _at(0.0, 0.0, 0.5))
        r.add_mesh(trimesh.creation.box((1.5, 1.5, 0.02)), _at(0.0, 0.0, 0.54))
        depth, seg = r.render(np.eye(4))
    noisy = FLYING_ONLY.apply(depth, np.random.default_rng(0))
    plate = seg == 0
    far = plate & (noisy - depth > 0.015)
    assert far.sum() > 10
    assert _supported(noisy)[far].any()  # the wall holds some up
    masked = DEPTH_FILTER.supported(noisy, INTRINSICS.fx, INTRINSICS.fy, plate)
    assert not masked[far].any() and not masked[~plate].any()
    assert masked[plate & (noisy == depth)].mean() >= 0.99


def test_a_noiseless_image_keeps_its_returns(box_wall):
    depth, seg = box_wall
    objects = seg >= 0
    assert _supported(depth)[objects].mean() >= 0.999
    assert not _supported(np.zeros_like(depth)).any()
    marked = depth.copy()
    marked[0, :3] = (np.nan, np.inf, -1.0)
    assert not _supported(marked)[0, :3].any()


def test_depth_to_points_cleans_unless_told_not_to(box_wall):
    depth, seg = box_wall
    noisy = FLYING_ONLY.apply(depth, np.random.default_rng(0))
    mask = seg == BOX
    cleaned = grid.depth_to_points(noisy, INTRINSICS, mask)
    raw = grid.depth_to_points(noisy, INTRINSICS, mask, cleaning=None)
    assert len(cleaned) < len(raw)
    assert cleaned[:, 2].max() < raw[:, 2].max() - 0.01  # the veil behind the box is gone


@pytest.fixture(scope="module")
def object_views():
    """Noiseless views (camera-frame points) of test-split objects, panning and on a table."""
    from completion.scenes import make_sequence

    views = []
    for condition in ("camera_pan", "tabletop"):
        for index in range(2):
            seq = make_sequence(condition, "test", index, 0, views=3, noise=False,
                                keep_depth=True)
            views += [grid.depth_to_points(seq.depth[t], INTRINSICS, seq.mask[t] >= 0)
                      for t in range(len(seq))]
    return views


def test_one_percent_of_points_5_cm_behind_barely_moves_the_grid(object_views):
    """1 % of a view's points moved 5 cm away along their viewing rays, as stray returns are:
    the fitted grid's side changes by under 2 % (the plain box grows by more)."""
    grew = 0
    for seed, points in enumerate(object_views):
        rng = np.random.default_rng(seed)
        pick = rng.choice(len(points), size=max(1, len(points) // 100), replace=False)
        moved = points.copy()
        moved[pick] += 0.05 * points[pick] / np.linalg.norm(points[pick], axis=1, keepdims=True)
        clean, _ = grid.fit_seen(points)
        stray, _ = grid.fit_seen(moved)
        assert abs(grid.pitch_of(stray) / grid.pitch_of(clean) - 1) < 0.02
        assert np.abs(stray[:3, 3] - clean[:3, 3]).max() < 0.02 * grid.pitch_of(clean) * 40
        grew += grid.pitch_of(grid.fit_grid(moved)) > 1.05 * grid.pitch_of(clean)
    assert grew >= len(object_views) // 3  # the plain box grows by 5-20 % on these


def test_clean_views_fit_close_to_the_plain_box(object_views):
    """On the renderer's noiseless views the fit stays the Varley fit of every point, or within
    2 % of it where a sparse part of the object (a face seen edge-on far away) is left out."""
    same = 0
    for points in object_views:
        fitted, plain = grid.fit_seen(points)[0], grid.fit_grid(points)
        assert abs(grid.pitch_of(fitted) / grid.pitch_of(plain) - 1) < 0.02
        same += bool(np.allclose(fitted, plain, atol=1e-12))
    assert same >= 0.8 * len(object_views)


def test_a_sparse_cloud_is_framed_whole():
    rng = np.random.default_rng(0)
    sparse = rng.uniform(-0.2, 0.2, size=(30, 3)) + [0.0, 0.0, 0.8]
    assert DEPTH_FILTER.inliers(sparse).all()
    fitted, _ = grid.fit_seen(sparse)
    np.testing.assert_allclose(fitted, grid.fit_grid(sparse))


@pytest.mark.parametrize("bad", [dict(min_angle_deg=0.0), dict(min_angle_deg=90.0),
                                 dict(min_support=9), dict(outlier_cell_m=0.0),
                                 dict(outlier_share=1.0)])
def test_filter_parameters_are_checked(bad):
    with pytest.raises(ValueError):
        DepthFilter(**bad)


def test_service_and_evaluation_make_the_same_grid_from_one_depth_image(client, tiny_model):
    """A tabletop view through the sensor model, posted as float32 metres with its mask and pose,
    is cleaned and framed by the service exactly as the evaluation's scene generator did."""
    from service_helpers import new_session, reference

    from completion.scenes import make_sequence
    from grasp_client.wire import depth_f32_m, intrinsics_field, mask_png

    seq = make_sequence("tabletop", "test", 1, 0, views=3, keep_depth=True)
    assert seq.meta["noise"]
    bodies = [{"depth": depth_f32_m(seq.depth[t]), "mask": mask_png(seq.mask[t] >= 0),
               "intrinsics": intrinsics_field(seq.meta["intrinsics"]),
               "camera_pose": seq.camera_to_world[t].tolist()} for t in range(len(seq))]
    session = new_session(client, bodies[0])
    answers = [client.post("/views", json=b | {"session_id": session}).json() for b in bodies[1:]]
    assert [a["observed_voxels"] for a in answers] == [int(seq.inputs[t].sum()) for t in (1, 2)]
    ref = reference(tiny_model, bodies)
    np.testing.assert_allclose(ref.completion().grid_to_camera, seq.grid_to_camera[-1],
                               atol=1e-12)
    # the cleaning is on in both: without it the view's points differ
    raw = grid.depth_to_points(seq.depth[-1], INTRINSICS, seq.mask[-1] >= 0, cleaning=None)
    cleaned = grid.depth_to_points(seq.depth[-1], INTRINSICS, seq.mask[-1] >= 0)
    assert len(cleaned) < len(raw)
