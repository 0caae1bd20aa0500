"""A simulated depth camera: pybullet DIRECT with the TinyRenderer (no GPU, no display).

``Renderer`` owns its pybullet client. Meshes are added as visual bodies with a world pose;
``render(camera_to_world)`` returns metric depth (z along the optical axis, metres, 0 where
nothing was hit) and a segmentation image holding the object index (−1 for background).

Camera conventions are those of :mod:`completion.grid`: OpenCV optical frame, poses camera→world.
The default intrinsics are :data:`completion.grid.DEFAULT_INTRINSICS` (320×240, 42.5° vertical
field of view, like an Intel RealSense D415 at low resolution).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from completion.grid import DEFAULT_INTRINSICS, Intrinsics

NEAR_M = 0.05
FAR_M = 4.0
#: OpenCV optical frame → OpenGL camera frame (y up, looking along −z).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class DepthNoise:
    """Depth-noise model for training: Gaussian on depth growing with z², plus pixel dropout.

    sigma(z) = sigma_base + sigma_quadratic · z²  (metres), as structured-light sensors behave.
    """

    sigma_base: float = 0.0005
    sigma_quadratic: float = 0.0015
    dropout: float = 0.02

    def apply(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        out = depth.copy()
        hit = out > 0
        z = out[hit]
        out[hit] = z + rng.normal(size=z.shape) * (self.sigma_base + self.sigma_quadratic * z**2)
        out[hit & (rng.random(out.shape) < self.dropout)] = 0.0
        return out


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """4×4 camera→world pose (OpenCV optical axes) of a camera at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along up: pick any perpendicular
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, eye
    return pose


def projection_matrix(
    intrinsics: Intrinsics, near: float = NEAR_M, far: float = FAR_M
) -> np.ndarray:
    """The OpenGL projection that images exactly as the pinhole ``intrinsics`` (row 0 = top)."""
    w, h = intrinsics.width, intrinsics.height
    p = np.zeros((4, 4))
    p[0, 0] = 2 * intrinsics.fx / w
    p[0, 2] = 1 - 2 * (intrinsics.cx + 0.5) / w
    p[1, 1] = 2 * intrinsics.fy / h
    p[1, 2] = 2 * (intrinsics.cy + 0.5) / h - 1
    p[2, 2] = -(far + near) / (far - near)
    p[2, 3] = -2 * far * near / (far - near)
    p[3, 2] = -1
    return p


class Renderer:
    """Owns a pybullet DIRECT client with mesh bodies; renders depth and segmentation."""

    def __init__(self, intrinsics: Intrinsics = DEFAULT_INTRINSICS) -> None:
        from completion.bullet import direct_client, pybullet

        self._pb = pybullet
        self.client = direct_client()
        self.intrinsics = intrinsics
        self._projection = projection_matrix(intrinsics).T.reshape(-1).tolist()
        self._bodies: list[int] = []

    def close(self) -> None:
        if self.client is not None:
            self.client.disconnect()
            self.client = None

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def add_mesh(self, mesh: trimesh.Trimesh, pose: np.ndarray | None = None) -> int:
        """Add a visual-only mesh body at ``pose`` (4×4 object→world); returns its object index."""
        vis = self.client.createVisualShape(
            self._pb.GEOM_MESH,
            vertices=np.asarray(mesh.vertices, dtype=np.float64).tolist(),
            indices=np.asarray(mesh.faces, dtype=np.int32).reshape(-1).tolist(),
            rgbaColor=[0.7, 0.7, 0.7, 1.0],
        )
        body = self.client.createMultiBody(baseMass=0, baseVisualShapeIndex=vis)
        self._bodies.append(body)
        self.set_pose(len(self._bodies) - 1, np.eye(4) if pose is None else pose)
        return len(self._bodies) - 1

    def set_pose(self, index: int, pose: np.ndarray) -> None:
        """Move object ``index`` to ``pose`` (4×4 object→world)."""
        quat = trimesh.transformations.quaternion_from_matrix(pose)  # w, x, y, z
        self.client.resetBasePositionAndOrientation(
            self._bodies[index], pose[:3, 3].tolist(), [quat[1], quat[2], quat[3], quat[0]]
        )

    def clear(self) -> None:
        for body in self._bodies:
            self.client.removeBody(body)
        self._bodies = []

    def render(self, camera_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Depth (H, W) float32 metres (0 = no return) and segmentation (H, W) int16 (−1 = none)."""
        view = (_CV_TO_GL @ np.linalg.inv(camera_to_world)).T.reshape(-1).tolist()
        w, h = self.intrinsics.width, self.intrinsics.height
        _, _, _, zbuf, seg = self.client.getCameraImage(
            w,
            h,
            viewMatrix=view,
            projectionMatrix=self._projection,
            renderer=self._pb.ER_TINY_RENDERER,
        )
        zbuf = np.asarray(zbuf, dtype=np.float64).reshape(h, w)
        seg = np.asarray(seg, dtype=np.int64).reshape(h, w)
        depth = FAR_M * NEAR_M / (FAR_M - (FAR_M - NEAR_M) * zbuf)
        index = np.full((h, w), -1, dtype=np.int16)
        for i, body in enumerate(self._bodies):
            index[seg == body] = i
        depth[index < 0] = 0.0
        return depth.astype(np.float32), index
