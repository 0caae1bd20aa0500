"""A fast screen of grasp candidates against a distance field, before the exact autograsp.

:class:`DistanceField` is the object's signed distance on a voxel grid (scipy's Euclidean
distance transform of the filled voxelization, outside positive), read with trilinear
interpolation; beyond the grid it falls back to the distance to the object's bounding box, a
lower bound. The hand is a cloud of points on its collision primitives' surfaces
(:func:`hand_cloud`), so every check below is one vectorised lookup for all candidates at once:

- :meth:`Screen.free`: is the open hand clear of the object at these palm poses?
- :meth:`Screen.approach`: how far each hand moves along its +z before touching (sphere tracing
  with the distance as a safe step).
- :meth:`Screen.predict`: where each approach stops, whether the palm is what touches, and how
  far the centre of mass then lies from the palm: what :func:`grasp.planner.plan` orders its
  candidates by before it autograsps only the most promising exactly.

It is approximate near contact: a point cloud and a voxel grid stand for the exact shapes, so
it agrees with the exact fcl check except within about a voxel of touching (the tests measure
how often). The planner uses a coarse cloud (``grasp.search.loop.SCREEN_SPACING_M``, 20 mm: 430
points) and nearest-voxel lookups: 64 candidates are screened in about 25 ms on this 2-core
machine, where their exact autograsps take about 0.9 s (``python -m grasp plan`` prints the
stages; ``--exact 0`` autograsps all).

With a support plane (``support_plane=``) the table is an obstacle too: a point's clearance is
the smaller of its distance to the object and its height above the plane. For the planner's
table candidates: :func:`open_hand_lowest` (exact primitives) and :func:`finger_reach`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import ndimage

from completion.grid import sample_surface
from grasp_client.wire import SupportPlane
from hands.barrett import BH8_282, JOINT_NAMES, BarrettParams, HandKinematics

#: Voxels of the distance field across the object's largest extent.
FIELD_VOXELS = 32
#: Spacing of the points sampled on the hand's primitives (metres).
CLOUD_SPACING_M = 0.006


@dataclass(frozen=True)
class DistanceField:
    """Signed distance (metres, negative inside) of a closed mesh on a padded voxel grid."""

    values: np.ndarray  # (nx, ny, nz) signed distance at voxel centres
    origin: np.ndarray  # (3,) centre of voxel (0, 0, 0)
    pitch: float
    lower: np.ndarray  # (3,) object's bounding box
    upper: np.ndarray

    @classmethod
    def of(
        cls, mesh: trimesh.Trimesh, *, voxels: int = FIELD_VOXELS, pad: int = 3
    ) -> DistanceField:
        """The field of ``mesh`` on a grid of ``voxels`` across its largest extent: the voxels
        that dense surface samples fall in, filled (closed shells), then the Euclidean distance
        transform both ways (about 10 ms for 32 voxels)."""
        pitch = float(mesh.extents.max()) / voxels
        origin = mesh.bounds[0] - pad * pitch  # centre of voxel (0, 0, 0)
        shape = np.ceil(mesh.extents / pitch).astype(int) + 2 * pad + 1
        samples = sample_surface(mesh.vertices, mesh.faces, spacing=pitch / 2)
        index = np.clip(np.rint((samples - origin) / pitch).astype(int), 0, shape - 1)
        shell = np.zeros(shape, dtype=bool)
        shell[tuple(index.T)] = True
        solid = ndimage.binary_fill_holes(shell)
        outside = ndimage.distance_transform_edt(~solid)
        inside = ndimage.distance_transform_edt(solid)
        # a voxel centre's distance to the surface: about half a voxel less than to the nearest
        # voxel centre of the other kind
        values = pitch * np.where(solid, 0.5 - inside, outside - 0.5)
        return cls(values, origin, pitch, mesh.bounds[0], mesh.bounds[1])

    def __call__(self, points: np.ndarray, *, nearest: bool = False) -> np.ndarray:
        """Signed distance at (..., 3) points; beyond the grid a lower bound (the larger of the
        distance to the object's bounding box and the field at the grid's edge minus the gap).
        ``nearest``: the nearest voxel's value instead of trilinear interpolation (about 4×
        faster, within half a voxel diagonal)."""
        p = np.asarray(points, dtype=np.float64)
        index = (p - self.origin) / self.pitch
        clamped = np.clip(index, 0, np.asarray(self.values.shape) - 1)
        if nearest:
            i, j, k = np.rint(clamped).astype(np.intp).transpose(-1, *range(p.ndim - 1))
            value = self.values[i, j, k]
        else:
            flat = clamped.reshape(-1, 3).T
            value = ndimage.map_coordinates(self.values, flat, order=1, mode="nearest")
            value = value.reshape(p.shape[:-1])
        gap = self.pitch * np.linalg.norm(index - clamped, axis=-1)
        outside = np.maximum(np.maximum(self.lower - p, p - self.upper), 0.0)
        return np.where(gap > 0, np.maximum(value - gap, np.linalg.norm(outside, axis=-1)), value)


def _box_surface(half: np.ndarray, spacing: float) -> np.ndarray:
    """Points on the surface of a box of half extents ``half``, at most ``spacing`` apart."""
    axes = [np.linspace(-h, h, max(2, int(np.ceil(2 * h / spacing)) + 1)) for h in half]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    on_face = np.any(np.isclose(np.abs(grid), half), axis=1)
    return grid[on_face]


def _cylinder_surface(radius: float, length: float, spacing: float) -> np.ndarray:
    n_around = max(8, int(np.ceil(2 * np.pi * radius / spacing)))
    angles = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    zs = np.linspace(-length / 2, length / 2, max(2, int(np.ceil(length / spacing)) + 1))
    ring = np.stack([radius * np.cos(angles), radius * np.sin(angles)], axis=1)
    side = np.concatenate([np.c_[ring, np.full(len(ring), z)] for z in zs])
    disks = []
    for r in np.arange(0.0, radius, spacing):
        k = max(1, int(np.ceil(2 * np.pi * r / spacing)))
        a = np.linspace(0, 2 * np.pi, k, endpoint=False)
        for z in (-length / 2, length / 2):
            disks.append(np.c_[r * np.cos(a), r * np.sin(a), np.full(k, z)])
    return np.concatenate([side, *disks])


def hand_cloud(
    kinematics: HandKinematics, spacing: float = CLOUD_SPACING_M
) -> dict[str, np.ndarray]:
    """Per link, (n, 4) homogeneous points on its collision primitives, in the link frame."""
    cloud: dict[str, list[np.ndarray]] = {}
    for prim in kinematics.primitives:
        if prim.kind == "box":
            local = _box_surface(0.5 * np.asarray(prim.size), spacing)
        else:
            local = _cylinder_surface(*prim.size, spacing)
        points = local @ prim.pose[:3, :3].T + prim.pose[:3, 3]
        cloud.setdefault(prim.link, []).append(points)
    return {link: np.c_[np.concatenate(p), np.ones(sum(len(x) for x in p))]
            for link, p in cloud.items()}


def open_hand_lowest(
    plane: SupportPlane, palms: np.ndarray, spreads_deg: np.ndarray, params=BH8_282
) -> np.ndarray:
    """(k,) height above ``plane`` of the lowest point of the open hand (its exact primitives)
    at (k, 4, 4) palm poses and (k,) spreads in degrees."""
    kinematics = _kinematics(params)
    lowest = np.full(len(palms), np.inf)
    for spread in np.unique(spreads_deg):
        sel = spreads_deg == spread
        links = kinematics.link_poses(np.radians([spread, 0, 0, spread, 0, 0, 0, 0]))
        for prim in kinematics.primitives:
            low = plane.lowest(prim.kind, prim.size, palms[sel] @ links[prim.link] @ prim.pose)
            lowest[sel] = np.minimum(lowest[sel], low)
    return lowest


@functools.lru_cache(maxsize=8)
def finger_reach(params: BarrettParams = BH8_282) -> float:
    """Deepest point (m below the palm face) that a freely closing finger passes through (J3 =
    J2 / 3, 1° steps): about 0.114 m for the BH8-282."""
    kinematics = _kinematics(params)
    below = SupportPlane(np.array([0.0, 0.0, -1.0]), 0.0)  # height = depth in the palm frame
    deepest = 0.0
    for links in _free_closing(params):
        for prim in kinematics.primitives_of("f1_prox") + kinematics.primitives_of("f1_dist"):
            depth = -below.lowest(prim.kind, prim.size, links[prim.link] @ prim.pose)
            deepest = max(deepest, float(depth))
    return deepest


@functools.lru_cache(maxsize=8)
def fingertip_span(params: BarrettParams = BH8_282) -> float:
    """Width (m) between opposing fingers where a closing finger reaches deepest below the palm
    (:func:`finger_reach`): what a grasp from above closes to at table level, about 0.11 m for
    the BH8-282 (finger 3's deepest point lies 57 mm from the palm's axis)."""
    kinematics = _kinematics(params)
    deepest, across = -np.inf, 0.0
    for links in _free_closing(params):
        for prim in kinematics.primitives_of("f3_dist"):
            points = (links[prim.link] @ prim.pose @ _corners(prim.kind, prim.size).T)[:3].T
            k = int(np.argmax(points[:, 2]))
            if points[k, 2] > deepest:
                deepest, across = points[k, 2], abs(points[k, 1])
    return 2.0 * across


def _free_closing(params: BarrettParams):
    """Every link's pose (palm frame) along a free closing, J3 = J2 / 3, in 1° steps of the DOF."""
    kinematics = _kinematics(params)
    for q in np.radians(np.arange(0.0, params.finger_dof_max_deg + 0.5, 1.0)):
        j2, j3 = min(q, np.radians(params.proximal_max_deg)), params.distal_ratio * q
        yield kinematics.link_poses(np.array([0.0, j2, j3, 0.0, j2, j3, j2, j3]))


def _corners(kind: str, size) -> np.ndarray:
    """(8, 4) homogeneous corners of a box (full extents), or of a cylinder's bounding box."""
    half = 0.5 * np.asarray(size) if kind == "box" else np.array([size[0], size[0], size[1] / 2])
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    return np.c_[signs * half, np.ones(8)]


@functools.lru_cache(maxsize=8)
def _kinematics(params: BarrettParams) -> HandKinematics:
    return HandKinematics(params)


@functools.lru_cache(maxsize=8)
def _hand_cloud(params: BarrettParams, spacing: float) -> dict[str, np.ndarray]:
    """:func:`hand_cloud` of a hand, built once per process."""
    return hand_cloud(HandKinematics(params), spacing)


class Screen:
    """The screen for one object: its distance field and the hand's point cloud (and the table,
    ``support_plane``, when there is one)."""

    def __init__(
        self,
        mesh: trimesh.Trimesh,
        *,
        params: BarrettParams = BH8_282,
        margin: float = 0.0,
        spacing: float = CLOUD_SPACING_M,
        nearest: bool = False,
        support_plane: SupportPlane | None = None,
    ) -> None:
        self.field = DistanceField.of(mesh)
        self.support_plane = support_plane
        self.kinematics = HandKinematics(params)
        self.cloud = _hand_cloud(params, spacing)
        self.margin = margin
        self.nearest = nearest  # nearest-voxel lookups (see DistanceField.__call__)
        self._open: dict[float, np.ndarray] = {}
        #: which points of :meth:`open_hand` lie on the palm
        self.palm_points = np.concatenate(
            [np.full(len(pts), link == "palm") for link, pts in self.cloud.items()]
        )

    def open_hand(self, spread_deg: float) -> np.ndarray:
        """(n, 3) points of the open hand at this spread, palm frame (cached per spread)."""
        key = float(spread_deg)
        if key not in self._open:
            joints = np.zeros(len(JOINT_NAMES))
            joints[[JOINT_NAMES.index("f1_spread"), JOINT_NAMES.index("f2_spread")]] = key
            poses = self.kinematics.link_poses(np.radians(joints))
            self._open[key] = np.concatenate(
                [(poses[link] @ pts.T)[:3].T for link, pts in self.cloud.items()]
            )
        return self._open[key]

    def _world(self, palms: np.ndarray, spreads_deg: np.ndarray, travel=None) -> np.ndarray:
        """(k, n, 3) the open hands at the palm poses, moved ``travel`` along their +z."""
        local = np.stack([self.open_hand(s) for s in spreads_deg])
        origin = palms[:, :3, 3]
        if travel is not None:
            origin = origin + travel[:, None] * palms[:, :3, 2]
        return np.einsum("kij,knj->kni", palms[:, :3, :3], local) + origin[:, None, :]

    def _gaps(self, hands: np.ndarray) -> np.ndarray:
        """(k, n) clearance of (k, n, 3) hand points: to the object, or the table if nearer."""
        gaps = self.field(hands, nearest=self.nearest)
        if self.support_plane is not None:
            gaps = np.minimum(gaps, self.support_plane.height(hands))
        return gaps

    def clearance(self, palms: np.ndarray, spreads_deg: np.ndarray) -> np.ndarray:
        """(k,) smallest signed distance from the open hand to the object (or the table) at
        each palm pose."""
        return self._gaps(self._world(palms, spreads_deg)).min(axis=1)

    def free(self, palms: np.ndarray, spreads_deg: np.ndarray) -> np.ndarray:
        """(k,) bool: the open hand is clear of the object (and the table) at each palm pose."""
        return self.clearance(palms, spreads_deg) > self.margin

    def approach(
        self, palms: np.ndarray, spreads_deg: np.ndarray, max_travel, tol: float = 1e-3
    ) -> np.ndarray:
        """(k,) travel along each palm's +z to first contact (``max_travel``, a number or (k,),
        if none): sphere tracing, each step the hand's clearance, which no point of the hand
        can cross."""
        travel = np.zeros(len(palms))
        limit = np.broadcast_to(np.asarray(max_travel, dtype=np.float64), travel.shape)
        active = np.ones(len(palms), dtype=bool)
        for _ in range(64):
            if not active.any():
                break
            idx = np.flatnonzero(active)
            hands = self._world(palms[idx], spreads_deg[idx], travel[idx])
            gap = self._gaps(hands).min(axis=1)
            done = (gap < tol) | (travel[idx] >= limit[idx])
            step = np.where(done, 0.0, np.maximum(gap, tol))
            travel[idx] = np.minimum(travel[idx] + step, limit[idx])
            active[idx[done]] = False
        return travel

    def predict(
        self, palms: np.ndarray, spreads_deg: np.ndarray, max_travel, center: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the planner orders its candidates by, for open hands approaching along their +z
        (at most ``max_travel``, a number or (k,)): (touches (k,) bool: the approach meets the
        object, not the table; palm (k,) bool: the palm is what touches it, within a voxel;
        depth (k,): distance (m) from the palm to ``center`` along the approach when it stops)."""
        travel = self.approach(palms, spreads_deg, max_travel)
        world = self._world(palms, spreads_deg, travel)
        hands = self.field(world, nearest=self.nearest)
        palm_gap = hands[:, self.palm_points].min(axis=1)
        touches = travel < max_travel
        if self.support_plane is not None:  # stopped by the object, not by the table
            touches &= hands.min(axis=1) <= self.support_plane.height(world).min(axis=1)
        palm = touches & (palm_gap <= hands.min(axis=1) + self.field.pitch)
        stop = palms[:, :3, 3] + travel[:, None] * palms[:, :3, 2]
        depth = np.einsum("ki,ki->k", np.asarray(center)[None, :] - stop, palms[:, :3, 2])
        return touches, palm, depth
