"""completion.mesh: a meshed grid lies where the grid transform says, with the right volume."""

import numpy as np
import pytest
import trimesh

from completion.grid import GRID_SHAPE, indices_to_points
from completion.mesh import EmptyMeshError, export_mesh, grid_to_mesh, load_mesh_bytes

PITCH = 0.005


def _transform(pitch: float = PITCH, origin=(-0.1, -0.08, 0.4)) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] *= pitch
    t[:3, 3] = origin
    return t


def _cube(lo=(10, 12, 8), n: int = 20) -> np.ndarray:
    g = np.zeros(GRID_SHAPE, dtype=bool)
    g[lo[0] : lo[0] + n, lo[1] : lo[1] + n, lo[2] : lo[2] + n] = True
    return g


def test_cube_volume_within_a_voxel_and_placed_by_the_transform():
    n, lo = 20, np.array([10, 12, 8])
    t = _transform()
    mesh = grid_to_mesh(_cube(tuple(lo), n), t, threshold=0.5)
    assert mesh.is_watertight and mesh.volume > 0
    # The iso-surface at 0.5 runs along the voxel boundaries (half a voxel outside the occupied
    # centres); marching cubes bevels the 12 edges, so the volume lies between the cube of the
    # occupied voxel centres, (n − 1)³, and the voxels' own volume n³, and within 1% of n³.
    voxel = PITCH**3
    assert (n - 1) ** 3 * voxel < mesh.volume <= n**3 * voxel
    assert mesh.volume == pytest.approx(n**3 * voxel, rel=0.01)
    # Flat faces sit exactly at the outer voxel boundaries, mapped through grid_to_camera.
    expected = indices_to_points(np.array([lo - 0.5, lo + n - 0.5]), t)
    np.testing.assert_allclose(mesh.bounds, expected, atol=1e-9)
    np.testing.assert_allclose(mesh.centroid, expected.mean(axis=0), atol=1e-9)


def test_outward_normals_and_threshold_on_probabilities():
    t = _transform(0.01, (0, 0, 0))
    p = np.zeros(GRID_SHAPE, dtype=np.float32)
    p[5:15, 5:15, 5:15] = 0.8
    p[15, 5:15, 5:15] = 0.4  # below 0.5, above 0.3
    small = grid_to_mesh(p, t, threshold=0.5)
    large = grid_to_mesh(p, t, threshold=0.3)
    assert small.volume > 0 and large.volume > small.volume
    # normals point away from the centre
    centre = small.centroid
    outward = np.einsum("ij,ij->i", small.face_normals, small.triangles_center - centre)
    assert (outward > 0).mean() > 0.99


def test_empty_grid_raises_and_export_round_trips():
    with pytest.raises(EmptyMeshError):
        grid_to_mesh(np.zeros(GRID_SHAPE), _transform(), threshold=0.5)
    mesh = grid_to_mesh(_cube(n=6), _transform(), threshold=0.5)
    for fmt in ("ply", "obj", "stl", "glb"):
        back = load_mesh_bytes(export_mesh(mesh, fmt), fmt)
        assert isinstance(back, trimesh.Trimesh)
        assert back.volume == pytest.approx(mesh.volume, rel=1e-4)
