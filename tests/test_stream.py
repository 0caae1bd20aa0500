"""completion.stream: which grid a view gets, and when a stream has seen the object."""

import numpy as np
import pytest

from completion import grid as G
from completion.config import ModelConfig
from completion.grid import GRID_SHAPE, VoxelGrid
from completion.model import build_model
from completion.stream import CompletionStream, NoObjectError
from grasp_client.wire import SupportPlane


def test_a_view_without_points_carries_the_grid_into_the_new_camera_frame():
    from completion.grid import carry_grid

    stream = CompletionStream(build_model(ModelConfig(kind="single_view", channels=(2, 2, 2))))
    rng = np.random.default_rng(0)
    points = rng.normal(scale=0.02, size=(200, 3)) + [0.0, 0.0, 0.5]
    camera = np.eye(4)
    stream.add_view(points=points, camera_to_world=camera)
    first = stream.grid_to_camera.copy()
    moved = np.eye(4)
    moved[:3, 3] = [1.0, 0.0, 0.0]  # the camera moved 1 m and sees nothing
    result = stream.add_view(points=np.zeros((0, 3)), camera_to_world=moved)
    assert result.observed_voxels == 0
    np.testing.assert_allclose(moved @ stream.grid_to_camera, camera @ first, atol=1e-12)
    np.testing.assert_allclose(stream.grid_to_camera, carry_grid(first, camera, moved))
    # without poses there is nothing to re-express: the grid stays as it was
    stream.add_view(points=np.zeros((0, 3)))
    np.testing.assert_allclose(stream.grid_to_camera, carry_grid(first, camera, moved))


def test_nothing_is_seen_until_a_view_has_an_observed_voxel():
    stream = CompletionStream(build_model(ModelConfig(kind="single_view", channels=(2, 2, 2))))
    empty = VoxelGrid(np.zeros(GRID_SHAPE, dtype=bool), np.diag([0.005, 0.005, 0.005, 1.0]))
    result = stream.add_view(grid=empty)
    assert result.occupied_voxels == 0 and not stream.seen
    with pytest.raises(NoObjectError):
        stream.completion()
    restored = CompletionStream.from_bytes(stream.model, stream.to_bytes())
    assert not restored.seen
    stream.add_view(points=np.random.default_rng(1).normal(scale=0.02, size=(50, 3)) + [0, 0, 0.5])
    assert stream.seen and stream.completion().views == 2


def test_a_still_camera_frames_every_point_it_saw_as_the_training_data_does():
    from completion.scenes import make_sequence

    seq = make_sequence("slide_behind", "test", 0, seed=0, keep_depth=True)
    intrinsics = G.Intrinsics(**{k: seq.meta["intrinsics"][k] for k in _INTRINSICS})
    model = build_model(ModelConfig(kind="single_view", channels=(2, 2, 2)))
    stream = CompletionStream(model)
    for t in range(len(seq.inputs)):
        if t == 6:  # a stored and restored session goes on exactly
            stream = CompletionStream.from_bytes(model, stream.to_bytes())
        result = stream.add_view(
            depth=seq.depth[t],
            intrinsics=intrinsics,
            mask=seq.mask[t] >= 0,
            camera_to_world=seq.camera_to_world[t],
        )
        np.testing.assert_allclose(stream.grid_to_camera, seq.grid_to_camera[t], atol=1e-12)
        assert result.observed_voxels == seq.inputs[t].sum()
    # without poses the stream cannot know the camera stood still: each view is fitted alone
    alone = CompletionStream(model)
    alone.add_view(depth=seq.depth[0], intrinsics=intrinsics, mask=seq.mask[0] >= 0)
    alone.add_view(depth=seq.depth[-1], intrinsics=intrinsics, mask=seq.mask[-1] >= 0)
    points = G.depth_to_points(seq.depth[-1], intrinsics, seq.mask[-1] >= 0)
    np.testing.assert_array_equal(alone.grid_to_camera, G.fit_seen(points)[0])
    assert not np.allclose(alone.grid_to_camera, seq.grid_to_camera[-1])


_INTRINSICS = ("fx", "fy", "cx", "cy", "width", "height")


def _posed_camera(rng):
    """A camera 0.5 m from the origin looking at it from a random direction above the table."""
    from completion.depth_camera import look_at

    elevation, azimuth = rng.uniform(0.3, 1.5), rng.uniform(0, 2 * np.pi)
    eye = 0.5 * np.array([np.cos(azimuth) * np.cos(elevation),
                          np.sin(azimuth) * np.cos(elevation), np.sin(elevation)])
    return look_at(eye, np.zeros(3))


def test_a_support_plane_cuts_every_completion_voxel_below_it():
    model = build_model(ModelConfig(kind="single_view", channels=(2, 2, 2)))
    rng = np.random.default_rng(3)
    for trial in range(6):
        stream = CompletionStream(model, threshold=0.3)
        table = SupportPlane([0.0, 0.0, 2.0], -2 * rng.uniform(-0.03, 0.03))  # normalised
        stream.set_support_plane(table)
        np.testing.assert_allclose(stream.support_plane.normal, [0, 0, 1])
        for _ in range(2):
            camera = _posed_camera(rng)
            world = rng.normal(scale=0.04, size=(300, 3))  # a blob straddling the table top
            points = G.transform_points(world, np.linalg.inv(camera))
            result = stream.add_view(points=points, camera_to_world=camera)
        c = stream.completion()
        centres = G.transform_points(c.voxel_grid().points(), camera)
        assert len(centres) == result.occupied_voxels > 0, trial
        assert (centres[:, 2] >= -stream.support_plane.offset - 1e-9).all(), trial
        # without the plane the same state reaches below it: the cut did the work
        plain = CompletionStream.from_bytes(model, stream.to_bytes())
        plain.support_plane = None
        below = G.transform_points(plain.completion().voxel_grid().points(), camera)[:, 2]
        assert (below < -table.offset).any(), trial


def test_the_support_plane_is_kept_with_the_state_and_needs_camera_poses():
    from completion.stream import stored_support_plane

    model = build_model(ModelConfig(kind="single_view", channels=(2, 2, 2)))
    points = np.random.default_rng(4).normal(scale=0.02, size=(50, 3)) + [0, 0, 0.5]
    stream = CompletionStream(model)
    stream.add_view(points=points)  # no camera pose
    floor = SupportPlane([0, 0, 1], 0.0)
    with pytest.raises(ValueError, match="camera poses"):
        stream.set_support_plane(floor)
    posed = CompletionStream(model)
    posed.add_view(points=points, camera_to_world=np.eye(4))
    posed.set_support_plane(SupportPlane([0, 0, 1], -0.1))
    assert stored_support_plane(stream.to_bytes()) is None
    np.testing.assert_array_equal(stored_support_plane(posed.to_bytes()).as_array(),
                                  [0, 0, 1, -0.1])
    restored = CompletionStream.from_bytes(model, posed.to_bytes())
    np.testing.assert_array_equal(restored.support_plane.as_array(), [0, 0, 1, -0.1])
    with pytest.raises(ValueError, match="needs its pose"):
        restored.add_view(points=points)
    with pytest.raises(ValueError, match="needs its pose"):
        CompletionStream(model).add_view(points=points, support_plane=floor)
    given = CompletionStream(model)
    given.add_view(points=points, camera_to_world=np.eye(4),
                   support_plane=SupportPlane([0, 0, 3], 0.3))
    np.testing.assert_allclose(given.support_plane.as_array(), [0, 0, 1, 0.1])
