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
class SensorModel:
    """What a structured-light or stereo depth camera does to a perfect depth image.

    Applied to a rendered depth image (metres, 0 = no return) by :meth:`apply`, in this order:

    1. **Axial noise** growing with z²: Gaussian with σ(z) = ``sigma_base`` +
       ``sigma_quadratic`` · (z − ``sigma_offset_m``)², the fit of Nguyen, Izadi and Lovell
       (3DIMPVT 2012) to a Kinect v1 at 10–60° incidence: σ = 1.2 mm + 1.9 mm/m² · (z − 0.4 m)²
       (1.2 mm at 0.4 m, 1.9 mm at 1 m).
    2. **Depth edges**: a pixel whose 4-neighbour is ``edge_jump_m`` (2 cm) or more further away,
       or has no return, is on an edge. A structured-light pattern is shadowed or smeared there,
       so an edge pixel returns nothing with probability ``edge_hole`` (0.3), or, with
       probability ``edge_flying`` (0.15), is a *flying pixel*: its depth is pulled a uniform
       fraction of the way towards the far neighbour (at most ``flying_max_m``, 5 cm, beyond
       it when the neighbour has no return), as the mixed returns of a real edge do.
    3. **Quantization** of disparity: depth is measured as disparity d = f·b/z, in steps of
       1/``subpixel`` pixel; with the Kinect v1's f = 580 px, b = 75 mm and 1/8-pixel steps
       (Khoshelham and Elberink, Sensors 2012) the depth step is z²/(f·b·8): 1.8 mm at 0.5 m,
       7.2 mm at 1 m.
    4. **Dropout**: each remaining return is lost with probability ``dropout`` (2 %), the
       scattered missing pixels of a real depth image.

    Every draw comes from the generator passed in, so a seeded scene is the same every time.
    ``SensorModel(edge_hole=0, edge_flying=0, subpixel=0, dropout=0)`` is Gaussian noise alone
    (``subpixel=0`` switches quantization off).
    """

    sigma_base: float = 0.0012
    sigma_quadratic: float = 0.0019
    sigma_offset_m: float = 0.4
    edge_jump_m: float = 0.02
    edge_hole: float = 0.3
    edge_flying: float = 0.15
    flying_max_m: float = 0.05
    focal_px: float = 580.0
    baseline_m: float = 0.075
    subpixel: int = 8
    dropout: float = 0.02

    def sigma(self, z: np.ndarray) -> np.ndarray:
        """Axial noise σ (metres) at depth ``z`` (metres)."""
        return self.sigma_base + self.sigma_quadratic * (np.asarray(z) - self.sigma_offset_m) ** 2

    def depth_step(self, z: np.ndarray) -> np.ndarray:
        """The quantization step of depth (metres) at ``z``: z² / (f · b · subpixel)."""
        return np.asarray(z) ** 2 / (self.focal_px * self.baseline_m * self.subpixel)

    def edges(self, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(on_edge, far): pixels with a return whose 4-neighbour is ``edge_jump_m`` further or
        empty, and the depth a flying pixel there falls towards (the farthest such neighbour,
        ``flying_max_m`` behind the pixel at most)."""
        hit = depth > 0
        padded = np.pad(depth, 1, mode="constant")
        far = np.zeros_like(depth)
        for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
            nb = padded[dy : dy + depth.shape[0], dx : dx + depth.shape[1]]
            nb = np.where(nb > 0, nb, np.inf)  # no return: as far as can be
            far = np.maximum(far, np.where(nb - depth >= self.edge_jump_m, nb, 0.0))
        on_edge = hit & (far > 0)
        far = np.minimum(far, depth + self.flying_max_m)
        return on_edge, far

    def apply(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The sensor's image of ``depth`` (H, W) float metres, 0 = no return; a new array."""
        depth = np.asarray(depth, dtype=np.float64)
        out = depth.copy()
        hit = depth > 0
        out[hit] += rng.normal(size=int(hit.sum())) * self.sigma(depth[hit])
        on_edge, far = self.edges(depth)
        u = rng.random(depth.shape)
        hole = on_edge & (u < self.edge_hole)
        flying = on_edge & (u >= self.edge_hole) & (u < self.edge_hole + self.edge_flying)
        out[flying] += rng.random(int(flying.sum())) * (far[flying] - depth[flying])
        out[hole] = 0.0
        if self.subpixel:
            fb = self.focal_px * self.baseline_m
            valid = out > 0
            disparity = np.round(fb / out[valid] * self.subpixel) / self.subpixel
            out[valid] = fb / np.maximum(disparity, 1.0 / self.subpixel)
        out[rng.random(depth.shape) < self.dropout] = 0.0
        return out.astype(np.float32)


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
