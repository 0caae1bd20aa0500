"""completion.stream: which grid a view gets, and when a stream has seen the object."""

import numpy as np
import pytest

from completion.grid import GRID_SHAPE, VoxelGrid
from completion.model import ModelConfig, build_model
from completion.stream import CompletionStream, NoObjectError


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
