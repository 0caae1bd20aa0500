"""Candidate pre-grasps: palm poses around an object, aimed at it, for :func:`grasp.planner.plan`.

Deterministic from ``seed``. Without a table (:func:`candidate_poses`):

1. Along the object's principal axes (±3 directions), with the fingers' opposition axis (palm y)
   laid along each of the two other principal axes, spreads 0° and 60° (24 poses). Boxes,
   cylinders and most man-made objects are grasped best this way.
2. The rest from a Fibonacci sphere of approach directions, randomly rotated by the seed, each
   with a seeded roll about the approach axis and a spread drawn from ``spreads_deg``.

Every candidate aims the palm's +z at the object's centre from outside its bounding sphere.
On a table (:func:`table_candidates`): top-down grasps first, fingertip grasps for a low object,
then the others that do not approach from below, every open hand started clear of the table.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh

from grasp.hand.collision import check_mesh, fibonacci_directions
from grasp.hand.pinch import TABLE_PINCH, TIP_CLEARANCE_M, pinch_height
from grasp.search.screen import finger_reach, open_hand_lowest
from grasp_client.wire import SupportPlane

#: Spreads (degrees) the random candidates draw from: parallel fingers, tripod, T, and between.
DEFAULT_SPREADS_DEG: tuple[float, ...] = (0.0, 30.0, 60.0, 90.0)
#: The palm starts this far outside the object's bounding sphere (metres).
STANDOFF_M = 0.02
#: Open hands start at least this far above the table (metres).
TABLE_CLEARANCE_M = 0.002
#: Fingertip grasps stop the palm this far above the closing fingers' deepest reach (metres), so
#: that the tips sweep just over the table.
PINCH_CLEARANCE_M = 0.004


@dataclass(frozen=True)
class Candidate:
    """One pre-grasp: palm→world (4, 4) pose aimed at the object, and a spread in degrees."""

    palm_pose: np.ndarray
    spread_deg: float
    source: str  # "principal", "sphere", or with a support plane "top", "pinch" (fingertips,
    # the palm still) or "table pinch" (the palm rising, grasp.hand.pinch)
    travel: float | None = None  # longest approach (metres); None: the planner's
    preshape_deg: float = 0.0  # the fingers' DOF on the way in (0: open; grasp.search.obstacles)


def principal_axes(mesh: trimesh.Trimesh) -> np.ndarray:
    """(3, 3) rows: the object's principal axes, longest extent first (area-weighted PCA).

    Signs are fixed (largest component positive) so that the axes are deterministic.
    """
    weights = mesh.area_faces / max(mesh.area, 1e-300)
    centroids = mesh.triangles_center
    mean = weights @ centroids
    centred = (centroids - mean) * np.sqrt(weights)[:, None]
    # full_matrices only for 1-2 faces (3 axes); for many faces it would build a faces² matrix
    _, _, axes = np.linalg.svd(centred, full_matrices=len(centred) < 3)
    axes = axes[:3]
    flip = np.sign(axes[np.arange(3), np.argmax(np.abs(axes), axis=1)])
    axes = axes * flip[:, None]
    if np.linalg.det(axes) < 0:
        axes[2] *= -1.0
    return axes


def _palm_pose(approach: np.ndarray, opposition: np.ndarray, target: np.ndarray, distance: float):
    """Palm pose with +z along ``approach``, +y near ``opposition``, ``distance`` before target."""
    z = approach / np.linalg.norm(approach)
    y = opposition - np.dot(opposition, z) * z
    if np.linalg.norm(y) < 1e-9:
        y = np.cross(z, np.eye(3)[int(np.argmin(np.abs(z)))])
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = x, y, z
    pose[:3, 3] = target - distance * z
    return pose


def candidate_poses(
    mesh: trimesh.Trimesh,
    *,
    n_candidates: int = 64,
    seed: int | np.random.Generator = 0,
    spreads_deg: Sequence[float] = DEFAULT_SPREADS_DEG,
    standoff: float = STANDOFF_M,
) -> list[Candidate]:
    """``n_candidates`` pre-grasp poses around ``mesh`` (principal-axis ones first)."""
    check_mesh(mesh)
    if n_candidates < 1:
        raise ValueError(f"n_candidates must be >= 1, got {n_candidates}")
    if not spreads_deg or any(not 0.0 <= s <= 180.0 for s in spreads_deg):
        raise ValueError(f"spreads_deg must be non-empty values in [0, 180], got {spreads_deg}")
    rng = np.random.default_rng(seed)
    center = np.asarray(mesh.bounds.mean(axis=0))
    distance = float(np.linalg.norm(mesh.vertices - center, axis=1).max()) + standoff
    axes = principal_axes(mesh)
    out: list[Candidate] = []
    for i in range(3):
        for sign in (1.0, -1.0):
            for j in (k for k in range(3) if k != i):
                for spread in (0.0, 60.0):
                    pose = _palm_pose(sign * axes[i], axes[j], center, distance)
                    out.append(Candidate(pose, spread, "principal"))
    n_sphere = max(n_candidates - len(out), 0)
    out = out[:n_candidates]
    if n_sphere:
        rotation = _random_rotation(rng)
        directions = fibonacci_directions(n_sphere) @ rotation.T
        rolls = rng.uniform(0.0, 2.0 * math.pi, n_sphere)
        spreads = rng.choice(np.asarray(spreads_deg, dtype=np.float64), n_sphere)
        for direction, roll, spread in zip(directions, rolls, spreads, strict=True):
            approach = -direction  # from the sphere point toward the centre
            base = _palm_pose(approach, np.eye(3)[int(np.argmin(np.abs(approach)))], center, 0.0)
            opposition = math.cos(roll) * base[:3, 1] + math.sin(roll) * base[:3, 0]
            pose = _palm_pose(approach, opposition, center, distance)
            out.append(Candidate(pose, float(spread), "sphere"))
    return out


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """(3, 3) uniformly random rotation (unit quaternion from four normals)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def table_candidates(
    mesh: trimesh.Trimesh,
    plane: SupportPlane,
    *,
    n_candidates: int = 64,
    seed: int | np.random.Generator = 0,
    spreads_deg: Sequence[float] = DEFAULT_SPREADS_DEG,
    standoff: float = STANDOFF_M,
    travel: float = 0.2,
) -> list[Candidate]:
    """``n_candidates`` pre-grasp poses around ``mesh`` resting on ``plane``: top-down ones
    (palm +z against the normal, fingers across each axis of the footprint, spreads 0° and 60°);
    for an object lower than the palm of a table pinch (:func:`grasp.hand.pinch.pinch_height`),
    table pinches (the same, the approach ending with the open hand's lowest point
    :data:`grasp.hand.pinch.TIP_CLEARANCE_M` above the table); for an object lower than the fingers'
    reach, fingertip ones (the same, the approach ending where the closing tips sweep just over
    the table); then :func:`candidate_poses`'s that do
    not approach from below. Every open hand starts clear of the table (:func:`_clear_of_table`;
    ``travel``: the others' approach, metres)."""
    check_mesh(mesh)
    if n_candidates < 1:
        raise ValueError(f"n_candidates must be >= 1, got {n_candidates}")
    center = np.asarray(mesh.bounds.mean(axis=0))
    distance = float(np.linalg.norm(mesh.vertices - center, axis=1).max()) + standoff
    axes = _footprint_axes(mesh, plane)[::-1]  # across the narrow side first
    tops = [(_palm_pose(-plane.normal, a, center, distance), s) for a in axes for s in (0.0, 60.0)]
    out = [Candidate(pose, spread, "top") for pose, spread in tops]
    if plane.height(mesh.vertices).max() < pinch_height():  # table pinches (grasp.hand.pinch)
        palms = np.stack([pose for pose, _ in tops])
        reach = open_hand_lowest(plane, palms, np.array([s for _, s in tops])) - TIP_CLEARANCE_M
        out += [Candidate(pose, spread, TABLE_PINCH, float(travel))
                for (pose, spread), travel in zip(tops, reach, strict=True)]
    pinch = finger_reach() + PINCH_CLEARANCE_M  # palm face height of a fingertip grasp
    if plane.height(mesh.vertices).max() < pinch:
        for pose, spread in tops:
            above, start = float(plane.height(pose[:3, 3])), pose.copy()
            start[:3, 3] += max(pinch - above, 0.0) * plane.normal
            out.append(Candidate(start, spread, "pinch", max(above - pinch, 0.0)))
    pool = candidate_poses(mesh, n_candidates=2 * n_candidates + 24, seed=seed,
                           spreads_deg=spreads_deg, standoff=standoff)
    out += [c for c in pool if c.palm_pose[:3, 2] @ plane.normal <= 1e-9]
    unique: dict[tuple, Candidate] = {}  # a top-down candidate may also be a principal one
    for c in out:  # (a table pinch starts where a top-down grasp does, and is another grasp)
        key = (c.source == TABLE_PINCH, c.spread_deg, (np.round(c.palm_pose, 9) + 0.0).tobytes())
        unique.setdefault(key, c)
    return _clear_of_table(list(unique.values())[:n_candidates], plane, travel)


def footprint(mesh: trimesh.Trimesh, plane: SupportPlane) -> tuple[float, float, float]:
    """The object's footprint on ``plane`` as its smallest enclosing rectangle's short and long
    sides, and its height above the plane (metres)."""
    n = plane.normal
    e1 = _palm_pose(n, np.zeros(3), np.zeros(3), 0.0)[:3, 0]  # any unit vector in the plane
    v = np.asarray(mesh.vertices)
    flat = v @ np.stack([e1, np.cross(n, e1)]).T  # (v, 2) in the plane
    _, sides = trimesh.bounds.oriented_bounds_2D(flat)
    return float(min(sides)), float(max(sides)), float(plane.height(v).max())


def _footprint_axes(mesh: trimesh.Trimesh, plane: SupportPlane) -> np.ndarray:
    """(2, 3) unit vectors in ``plane``: the object's footprint's long axis, then the short one
    (area-weighted PCA of the faces projected on the plane; largest component positive)."""
    n = plane.normal
    e1 = _palm_pose(n, np.zeros(3), np.zeros(3), 0.0)[:3, 0]  # any unit vector in the plane
    basis = np.stack([e1, np.cross(n, e1)])  # (2, 3)
    weights = mesh.area_faces / max(mesh.area, 1e-300)
    centroids = mesh.triangles_center
    flat = (centroids - weights @ centroids) @ basis.T  # (f, 2)
    _, vectors = np.linalg.eigh((flat * weights[:, None]).T @ flat)
    long = vectors[:, 1] @ basis
    long *= np.sign(long[np.argmax(np.abs(long))])
    return np.stack([long, np.cross(n, long)])


def _clear_of_table(
    candidates: Sequence[Candidate], plane: SupportPlane, travel: float
) -> list[Candidate]:
    """The candidates, each open hand less than :data:`TABLE_CLEARANCE_M` above ``plane`` moved
    back along its approach (if it descends at least 30°) or up the normal."""
    palms = np.stack([c.palm_pose for c in candidates])
    lowest = open_hand_lowest(plane, palms, np.array([c.spread_deg for c in candidates]))
    out = []
    for c, low in zip(candidates, lowest, strict=True):
        need = TABLE_CLEARANCE_M - float(low)
        pose, limit = c.palm_pose.copy(), travel if c.travel is None else c.travel
        descent = -float(pose[:3, 2] @ plane.normal)
        if need <= 0.0:
            out.append(c)
        elif descent >= 0.5:  # keep the approach line: start further back
            pose[:3, 3] -= need / descent * pose[:3, 2]
            out.append(dataclasses.replace(c, palm_pose=pose, travel=limit + need / descent))
        else:
            pose[:3, 3] += need * plane.normal
            out.append(dataclasses.replace(c, palm_pose=pose, travel=limit))
    return out
