import numpy as np
import pytest
import trimesh

from completion import grid as G
from completion.depth import DEPTH_FILTER


def test_round_trip_points_indices_within_half_voxel():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.1, 0.1, (500, 3)) + [0, 0, 0.6]
    t = G.fit_grid(pts)
    back = G.indices_to_points(G.points_to_indices(pts, t), t)
    pitch = G.VoxelGrid(np.zeros(G.GRID_SHAPE, bool), t).pitch
    assert np.abs(back - pts).max() <= pitch / 2 + 1e-12


def test_fit_on_hand_computed_example():
    # bbox x∈[0, 0.32], y∈[0, 0.16], z∈[1.0, 1.08]: centre (0.16, 0.08, 1.04), largest extent
    # 0.32 m → pitch 0.01 m; index (20, 20, 18) must map to the centre.
    pts = np.array([[0.0, 0.0, 1.0], [0.32, 0.16, 1.08], [0.1, 0.1, 1.02]])
    t = G.fit_grid(pts)
    assert t[0, 0] == pytest.approx(0.01) and t[1, 1] == pytest.approx(0.01)
    np.testing.assert_allclose(G.indices_to_points([[20, 20, 18]], t)[0], [0.16, 0.08, 1.04])
    idx = G.points_to_indices(pts[:2], t, rounded=False)
    np.testing.assert_allclose(idx[1, 0] - idx[0, 0], 32.0)  # the largest extent spans 32 voxels
    np.testing.assert_allclose(idx[0], [4.0, 12.0, 14.0])


def test_fit_rejects_bad_points():
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        G.fit_grid(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="finite"):
        G.fit_grid(np.array([[0.0, np.nan, 1.0]]))
    with pytest.raises(ValueError, match="at least one"):
        G.fit_grid(np.zeros((0, 3)))


def _sphere_grid(radius=0.05, faces_kept=None):
    m = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    v = m.vertices + [0.0, 0.0, 0.5]
    t = G.fit_grid(v)
    f = m.faces if faces_kept is None else m.faces[faces_kept]
    return G.voxelize_mesh(v, f, t), t


def test_sphere_volume_matches_analytic():
    occ, t = _sphere_grid()
    pitch = G.VoxelGrid(occ, t).pitch
    assert occ.sum() * pitch**3 == pytest.approx(4 / 3 * np.pi * 0.05**3, rel=0.05)


def test_mesh_with_holes_still_solid():
    full, _ = _sphere_grid()
    keep = np.random.default_rng(0).random(5120) > 0.10
    holed, _ = _sphere_grid(faces_kept=keep)
    iou = (full & holed).sum() / (full | holed).sum()
    assert iou >= 0.95
    assert holed[20, 20, 18]  # the centre is filled: solid, not a hollow shell


def test_thin_plate_is_kept():
    plate = trimesh.creation.box(extents=[0.2, 0.2, 0.001])  # far thinner than a voxel
    v = plate.vertices + [0, 0, 0.5]
    occ = G.voxelize_mesh(v, plate.faces, G.fit_grid(v))
    assert occ.sum() > 32 * 32 * 0.9


def test_random_urdf_mesh_gives_nonempty_solid():
    from completion.objects import load_object

    m = load_object("urdf/903")
    v = m.vertices + [0, 0, 0.6]
    occ = G.voxelize_mesh(v, m.faces, G.fit_grid(v))
    assert occ.sum() > 100
    # Interior voxels exist (solid): eroding once leaves something.
    from scipy import ndimage

    assert ndimage.binary_erosion(occ).sum() > 0


def test_depth_to_points_recovers_plane_distance():
    from completion.depth_camera import Renderer, look_at

    with Renderer() as r:
        r.add_mesh(
            trimesh.creation.box(extents=[2, 2, 0.01]),
            trimesh.transformations.translation_matrix([0, 0, -0.005]),
        )
        cam = look_at([0.0, 0.0, 0.7], [0, 0, 0], up=[0, 1, 0])
        depth, mask = r.render(cam)
    pts = G.depth_to_points(depth, G.DEFAULT_INTRINSICS, mask >= 0)
    assert len(pts) == 320 * 240
    np.testing.assert_allclose(pts[:, 2], 0.7, atol=1e-3)
    world = G.transform_points(pts, cam)
    np.testing.assert_allclose(world[:, 2], 0.0, atol=1e-3)


def test_depth_to_points_checks_shapes():
    intr = G.DEFAULT_INTRINSICS
    with pytest.raises(ValueError, match="height, width"):
        G.depth_to_points(np.ones((10, 10)), intr)
    with pytest.raises(ValueError, match="mask"):
        G.depth_to_points(np.ones((240, 320)), intr, np.ones((10, 10)))
    line = np.where(np.eye(240, 320) > 0, 1.0, np.nan)
    assert len(G.depth_to_points(line, intr, cleaning=None)) == 240  # NaN: no return
    assert len(G.depth_to_points(line, intr)) == 238  # cleaned: the line's ends lack support


def test_voxel_grid_pack_round_trip():
    occ = np.random.default_rng(1).random(G.GRID_SHAPE) > 0.7
    assert np.array_equal(G.VoxelGrid.unpack(G.VoxelGrid(occ, np.eye(4)).pack()), occ)
    with pytest.raises(ValueError, match="8000 bytes"):
        G.VoxelGrid.unpack(b"123")


def test_fit_seen_frames_every_point_seen_from_a_still_camera():
    rng = np.random.default_rng(0)
    left = rng.normal(scale=0.02, size=(100, 3)) + [-0.1, 0.0, 0.5]
    right = rng.normal(scale=0.02, size=(100, 3)) + [0.1, 0.0, 0.6]
    framing = [p[DEPTH_FILTER.inliers(p)] for p in (left, right)]  # sparse tails left out
    assert 0.5 * len(left) < len(framing[0]) < len(left)
    t, seen = G.fit_seen(left)  # a new pose: the plain per-view fit
    np.testing.assert_array_equal(t, G.fit_grid(framing[0]))
    t, seen = G.fit_seen(right, seen)  # the same pose again: the box of both
    np.testing.assert_array_equal(t, G.fit_grid(np.concatenate(framing)))
    assert G.in_grid(G.points_to_indices(left, t)).all()
    t_empty, kept = G.fit_seen(np.zeros((0, 3)), seen)  # nothing visible now: the same grid
    np.testing.assert_array_equal(t_empty, t)
    np.testing.assert_array_equal(kept, seen)
    assert G.fit_seen(np.zeros((0, 3))) == (None, None)
    with pytest.raises(ValueError, match=r"\(2, 3\)"):
        G.fit_seen(left, np.zeros(3))
    assert G.camera_still(np.eye(4), np.eye(4) + 1e-9)
    assert not G.camera_still(np.eye(4), None) and not G.camera_still(np.eye(4), 2 * np.eye(4))
