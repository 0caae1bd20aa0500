"""Occupancy grid → metric triangle mesh (docs/design.md §6), and mesh export.

Marching cubes (scikit-image) runs on the occupancy probabilities padded by one voxel of zeros
so the surface always closes, at the decision threshold; vertices (in fractional voxel indices)
are mapped to metres in the camera frame through ``grid_to_camera``. A bool grid works too (it is
meshed at 0.5).
"""

from __future__ import annotations

import io
from typing import Literal

import numpy as np
import trimesh

from completion.grid import GRID_SHAPE, indices_to_points

MeshFormat = Literal["ply", "obj", "stl", "glb"]
MESH_FORMATS: tuple[str, ...] = ("ply", "obj", "stl", "glb")


class EmptyMeshError(ValueError):
    """The grid has no voxel at or above the threshold, so there is no surface."""


def grid_to_mesh(
    probabilities: np.ndarray,
    grid_to_camera: np.ndarray,
    *,
    threshold: float = 0.5,
    oriented: bool = True,
) -> trimesh.Trimesh:
    """Mesh of the iso-surface ``probabilities == threshold``, vertices in metres (camera frame).

    probabilities : (40, 40, 40) float in [0, 1] or bool
    grid_to_camera : (4, 4) float
    oriented : merge and clean up with trimesh and make the normals point outward (what grasping
        and export need); False gives marching cubes' triangles as they are, faster, enough for
        sampling the surface
    Raises EmptyMeshError when nothing reaches the threshold.
    """
    from skimage.measure import marching_cubes

    p = np.asarray(probabilities)
    if p.shape != GRID_SHAPE:
        raise ValueError(f"probabilities must be {GRID_SHAPE}, got {p.shape}")
    if not 0.0 < threshold < 1.0:
        raise ValueError(f"threshold must lie in (0, 1), got {threshold}")
    p = p.astype(np.float32)
    if not (p >= threshold).any():
        raise EmptyMeshError("no voxel reaches the threshold: the completion is empty")
    padded = np.pad(p, 1, mode="constant", constant_values=0.0)
    verts, faces, _, _ = marching_cubes(padded, level=threshold)
    verts = verts - 1.0  # undo the padding: back to the grid's voxel indices
    # skimage orients faces by the gradient toward higher values; flip so normals point outward.
    points = indices_to_points(verts, grid_to_camera)
    if not oriented:
        return trimesh.Trimesh(points, faces, process=False)
    mesh = trimesh.Trimesh(points, faces[:, ::-1], process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def export_mesh(mesh: trimesh.Trimesh, file_format: str) -> bytes:
    """The mesh as PLY (binary), OBJ, STL (binary) or GLB bytes."""
    if file_format not in MESH_FORMATS:
        raise ValueError(f"mesh format must be one of {MESH_FORMATS}, got {file_format!r}")
    data = mesh.export(file_type=file_format)
    if isinstance(data, str):
        data = data.encode()
    return bytes(data)


def load_mesh_bytes(data: bytes, file_format: str) -> trimesh.Trimesh:
    """Inverse of :func:`export_mesh` (used by tests and clients)."""
    return trimesh.load(io.BytesIO(data), file_type=file_format, force="mesh")
