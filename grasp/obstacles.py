"""Obstacles beside the object: the neighbours on a table, which the hand must not touch.

A robot's table is rarely empty. The planner is given what it must keep clear of as a set of
occupied voxels (:class:`Obstacles`, the centres of cubes of side ``pitch``, in any orientation),
in the frame of the mesh it plans on: the voxels the service saw around the target (every
non-table pixel that is not the target's, back-projected), or the surfaces of the neighbours'
true meshes in the evaluation. Voxels, not meshes: a depth camera sees the neighbours' near
sides only, and a voxel set of a stated pitch is bounded however many views add to it.

The hand keeps clear of them while it moves as the planner plans it (:func:`sweep_hit`):

1. the open hand's approach, a straight line from the pre-grasp to where the autograsp stopped
   (exact for the links' bounding boxes: each box swept along a segment);
2. the closing, from the open hand to the closed one (the palm rising with a table pinch),
   every :data:`CLOSING_STEP_DEG` of joint motion: between two samples each box is swept along
   its centre's motion and grown by what its turn adds, so that nothing between is missed.

Each voxel is a cube, so a box reaches it when the box grown by half the voxel's diagonal holds
its centre (conservative by at most that much). A grasp whose hand reaches an obstacle is
refused by the planner with the reason (:func:`hit_reason`). The lift that follows is not
checked: it moves the hand away from the table, away from neighbours standing on it.

This module must not import torch (docs/design.md §2).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from completion.grid import OBSTACLE_PITCH_M, voxel_keys
from hands.barrett import BH8_282, FINGERS, LINK_NAMES, BarrettParams, HandKinematics
from hands.barrett.kinematics import joints_from_dofs

__all__ = ["CLOSING_STEP_DEG", "DEFAULT_PITCH_M", "Hit", "Obstacles", "hit_reason", "seen_others",
           "sweep_hit"]

#: Side of an obstacle voxel (metres): fine beside a 2-10 cm gap, bounded in count; the one a
#: session keeps its obstacles at.
DEFAULT_PITCH_M = OBSTACLE_PITCH_M
#: What a view's other pixels keep as obstacles (:func:`seen_others`): points higher than this
#: above the table (m; lower ones are the table), within this reach of the target's points
#: (m, horizontally: what a hand grasping it can meet), and farther than this from them (m: a
#: label image's rim around the target, flying pixels, are not a neighbour).
ABOVE_TABLE_M = 0.01
REACH_M = 0.3
TARGET_MARGIN_M = 0.01
#: The closing is checked every this many degrees of joint motion (a finger link's box is grown
#: by about 2 mm for its turn between two samples).
CLOSING_STEP_DEG = 2.5


class Obstacles:
    """Occupied voxels to keep the hand clear of: (n, 3) centres of cubes of side ``pitch``, in
    any orientation (a cube is tested by its half diagonal, :attr:`reach`, so voxels of a grid
    moved into another frame need no new grid)."""

    def __init__(self, centres: np.ndarray, pitch: float = DEFAULT_PITCH_M) -> None:
        self.centres, self.pitch = _checked(centres, pitch)
        self._tree = cKDTree(self.centres) if len(self.centres) else None

    @classmethod
    def from_points(cls, points: np.ndarray, pitch: float = DEFAULT_PITCH_M) -> Obstacles:
        """The voxels of side ``pitch`` that hold ``points`` (a depth camera's), each once
        (:func:`completion.grid.voxel_keys`), so that views of one surface add nothing twice."""
        points, pitch = _checked(points, pitch)
        return cls((np.unique(voxel_keys(points, pitch), axis=0) + 0.5) * pitch, pitch)

    @classmethod
    def from_meshes(cls, meshes: Sequence[trimesh.Trimesh],
                    pitch: float = DEFAULT_PITCH_M) -> Obstacles:
        """The surfaces of ``meshes`` (the neighbours), voxelised at ``pitch``."""
        points = [m.voxelized(pitch).points for m in meshes if len(m.faces)]
        return cls(np.concatenate(points) if points else np.zeros((0, 3)), pitch)

    def __len__(self) -> int:
        return len(self.centres)

    @property
    def reach(self) -> float:
        """How far from a voxel's centre its cube reaches (half its diagonal)."""
        return 0.5 * math.sqrt(3.0) * self.pitch

    def near(self, centre: np.ndarray, radius: float) -> np.ndarray:
        """The voxel centres within ``radius`` (+ :attr:`reach`) of ``centre``."""
        if self._tree is None:
            return self.centres
        return self.centres[self._tree.query_ball_point(centre, radius + self.reach)]

    def transformed(self, matrix: np.ndarray) -> Obstacles:
        """The same voxels moved by the rigid ``matrix`` (4, 4)."""
        matrix = np.asarray(matrix, dtype=np.float64)
        return Obstacles(self.centres @ matrix[:3, :3].T + matrix[:3, 3], self.pitch)


def _checked(points: np.ndarray, pitch: float) -> tuple[np.ndarray, float]:
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not pitch > 0.0:
        raise ValueError(f"pitch must be positive, got {pitch}")
    if not np.isfinite(points).all():
        raise ValueError("obstacle points must be finite")
    return points, float(pitch)


def seen_others(others: np.ndarray, target: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """Which of a view's other points (not the target's, world frame, (m, 3)) are obstacles:
    above the table ``plane`` ((4,), n·x + d = 0, n up) by :data:`ABOVE_TABLE_M`, within
    :data:`REACH_M` of the target's points ``target`` ((n, 3), world) along the table, and not
    within :data:`TARGET_MARGIN_M` of them. One rule for the service's views and the
    evaluation's (:func:`grasp.evaluate.clutter.seen_obstacles`)."""
    others = np.asarray(others, dtype=np.float64).reshape(-1, 3)
    target = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    if len(others) == 0 or len(target) == 0:
        return others[:0]
    normal, offset = np.asarray(plane[:3], float), float(plane[3])
    others = others[others @ normal + offset > ABOVE_TABLE_M]
    if len(others) == 0:
        return others

    def flat(p: np.ndarray) -> np.ndarray:  # projected onto the table
        return p - np.outer(p @ normal + offset, normal)

    along, _ = cKDTree(flat(target)).query(flat(others), distance_upper_bound=REACH_M)
    others = others[np.isfinite(along)]
    if len(others):
        distance, _ = cKDTree(target).query(others)
        others = others[distance > TARGET_MARGIN_M]
    return others


@dataclass(frozen=True)
class Hit:
    """Where a planned motion reaches an obstacle: the hand's link, the motion's phase
    ("approach" or "closing") and the obstacle voxel's centre."""

    link: str
    phase: str
    point: np.ndarray


def _box_sweep_hits(points: np.ndarray, pose: np.ndarray, half: np.ndarray,
                    move: np.ndarray) -> np.ndarray:
    """Which ``points`` the box (``pose``: box→world, ``half``: half extents) reaches while it
    translates by ``move`` (world): slab intervals of the motion parameter s in [0, 1]."""
    rot, centre = pose[:3, :3], pose[:3, 3]
    q = (points - centre) @ rot  # the points in the box frame
    u = rot.T @ move
    lo, hi = np.zeros(len(points)), np.ones(len(points))
    for axis in range(3):
        if abs(u[axis]) < 1e-12:
            inside = np.abs(q[:, axis]) <= half[axis]
            lo = np.where(inside, lo, 2.0)
            continue
        a = (q[:, axis] - half[axis]) / u[axis]
        b = (q[:, axis] + half[axis]) / u[axis]
        lo, hi = np.maximum(lo, np.minimum(a, b)), np.minimum(hi, np.maximum(a, b))
    return lo <= hi


#: What growing a finger link's box for a voxel's size and its turn between two closing samples
#: adds at most to how far it reaches (m; √3 × (4.3 mm + 4 cm × 5°) is 14 mm).
GROWTH_MARGIN_M = 0.02
#: The links that turn while the fingers close, and each finger's (J2, J3) in the 8 joints.
FINGER_LINKS = ("_prox", "_dist")
_FINGER_JOINTS = ((1, 2), (4, 5), (6, 7))


class _Hand:
    """The hand's links as boxes (each primitive's bounding box) for obstacle tests."""

    def __init__(self, params: BarrettParams) -> None:
        self.kinematics = HandKinematics(params)
        self.params = params
        self.boxes = {link: [(prim.pose, prim.half_extents())
                             for prim in self.kinematics.primitives_of(link)]
                      for link in LINK_NAMES}
        # how far a finger's boxes reach from its knuckle, at any of its joints (sampled)
        reach = 0.0
        for q in np.radians(np.arange(0.0, params.finger_dof_max_deg + 1.0, 10.0)):
            for link, pose in zip(("f1_prox", "f1_dist"), self.kinematics.finger_poses(
                    np.eye(4), "f1", min(q, np.radians(params.proximal_max_deg)),
                    q * params.distal_ratio), strict=True):
                for local, half in self.boxes[link]:
                    box = pose @ local
                    reach = max(reach, float(np.linalg.norm(box[:3, 3]) + np.linalg.norm(half)))
        self.finger_reach = reach
        # and how far a knuckle lies from the palm's origin, at any spread
        self.knuckle_reach = max(
            float(np.linalg.norm(self.kinematics.knuckle_pose(f, s)[:3, 3]))
            for f in FINGERS for s in np.radians([0.0, 90.0, 180.0]))

    def world_boxes(self, palm: np.ndarray, joints_rad: np.ndarray):
        """(link, box→world, half extents) of every primitive."""
        for link, pose in self.kinematics.link_poses(joints_rad).items():
            for local, half in self.boxes[link]:
                yield link, palm @ pose @ local, half


_HANDS: dict[BarrettParams, _Hand] = {}


def _hand(params: BarrettParams) -> _Hand:
    if params not in _HANDS:
        _HANDS[params] = _Hand(params)
    return _HANDS[params]


def _first_hit(obstacles: Obstacles, boxes, move: np.ndarray, grow: float,
               phase: str) -> Hit | None:
    """The first of ``boxes`` (link, box→world, half extents) that reaches a voxel while moving
    by ``move``: one look-up of the voxels near them all, then each box's own."""
    boxes = list(boxes)
    if not boxes:
        return None
    centres = np.array([pose[:3, 3] for _, pose, _ in boxes]) + 0.5 * move
    halves = [half + obstacles.reach + grow for _, _, half in boxes]
    reach = np.array([np.linalg.norm(h) for h in halves]) + 0.5 * float(np.linalg.norm(move))
    middle = 0.5 * (centres.min(axis=0) + centres.max(axis=0))
    near = obstacles.near(middle, float((np.linalg.norm(centres - middle, axis=1) + reach).max()))
    if len(near) == 0:
        return None
    for (link, pose, _), half, centre, r in zip(boxes, halves, centres, reach, strict=True):
        mine = near[np.linalg.norm(near - centre, axis=1) <= r]
        if len(mine) == 0:
            continue
        hits = _box_sweep_hits(mine, pose, half, move)
        if hits.any():
            return Hit(link, phase, mine[int(np.argmax(hits))])
    return None


def sweep_hit(
    obstacles: Obstacles | None,
    start_pose: np.ndarray,
    palm_pose: np.ndarray,
    joints_deg: Sequence[float],
    *,
    end_palm_pose: np.ndarray | None = None,
    preshape_deg: float = 0.0,
    params: BarrettParams = BH8_282,
) -> Hit | None:
    """The first place where the hand, moving as planned, reaches an obstacle (None: clear).

    ``start_pose``: the pre-grasp palm pose (the open hand, fingers at the grasp's spread);
    ``palm_pose``: where the approach stopped and closing starts; ``joints_deg``: the closed
    hand's 8 joints; ``end_palm_pose``: where the palm is when closing ends (a table pinch's
    rise; default ``palm_pose``); ``preshape_deg``: the fingers' DOF on the way in (0: open)."""
    if obstacles is None or len(obstacles) == 0:
        return None
    hand = _hand(params)
    closed = np.radians(np.asarray(joints_deg, dtype=np.float64))
    # the spread is set before the approach, the fingers at their pre-shape
    spread = float(np.degrees(closed[0]))
    opened = np.radians(joints_from_dofs([spread, *[preshape_deg] * 3], params=params))
    start, stop = np.asarray(start_pose, float), np.asarray(palm_pose, float)
    end = stop if end_palm_pose is None else np.asarray(end_palm_pose, float)
    hit = _first_hit(obstacles, hand.world_boxes(start, opened), stop[:3, 3] - start[:3, 3], 0.0,
                     "approach")
    if hit is not None:
        return hit
    if np.allclose(closed, opened) and np.allclose(end, stop):
        return None  # nothing moves after the approach
    # the palm and the knuckles (the spread is set) move only with a pinch's rise: swept along it
    fixed = [box for box in hand.world_boxes(stop, opened) if not box[0].endswith(FINGER_LINKS)]
    hit = _first_hit(obstacles, fixed, end[:3, 3] - stop[:3, 3], 0.0, "closing")
    if hit is not None:
        return hit
    travel = float(np.max(np.abs(np.degrees(closed - opened))))
    steps = max(1, math.ceil(travel / CLOSING_STEP_DEG))
    # between two samples each finger link's box is swept along its centre's motion and grown
    # by what its turn adds: a link turns by at most its joints' change (the distal's
    # orientation is J2 + J3), its corners by its half diagonal times that
    turn = 2.0 * math.radians(travel) / steps
    palms = [stop.copy() for _ in range(steps + 1)]
    for k, palm in enumerate(palms):  # a pinch's palm rises while the fingers close
        palm[:3, 3] = (1.0 - k / steps) * stop[:3, 3] + (k / steps) * end[:3, 3]
    rise = float(np.linalg.norm(end[:3, 3] - stop[:3, 3]))
    reach = hand.finger_reach + GROWTH_MARGIN_M  # a finger's boxes, grown, from its knuckle
    hand_near = obstacles.near(0.5 * (stop[:3, 3] + end[:3, 3]),  # within any finger's reach
                               0.5 * rise + hand.knuckle_reach + reach)
    if len(hand_near) == 0:
        return None
    for finger, (i2, i3) in zip(FINGERS, _FINGER_JOINTS, strict=True):
        knuckle = hand.kinematics.knuckle_pose(finger, float(closed[0]))
        ends = [palms[0] @ knuckle, palms[-1] @ knuckle]
        around = 0.5 * (ends[0][:3, 3] + ends[1][:3, 3])
        span = 0.5 * float(np.linalg.norm(ends[1][:3, 3] - ends[0][:3, 3]))
        near = hand_near[np.linalg.norm(hand_near - around, axis=1) <= span + reach]
        if len(near) == 0:
            continue  # nothing within this finger's reach: it closes clear
        samples = []
        for k in range(steps + 1):
            s = k / steps
            j2, j3 = (1 - s) * opened[i2] + s * closed[i2], (1 - s) * opened[i3] + s * closed[i3]
            poses = hand.kinematics.finger_poses(palms[k] @ knuckle, finger, j2, j3)
            samples.append([(link, pose @ local, half)
                            for link, pose in zip((f"{finger}_prox", f"{finger}_dist"), poses,
                                                  strict=True)
                            for local, half in hand.boxes[link]])
        for j, (link, _, half) in enumerate(samples[0]):
            grown = half + obstacles.reach + float(np.linalg.norm(half)) * turn
            centres = np.array([boxes[j][1][:3, 3] for boxes in samples])
            middle = 0.5 * (centres.min(axis=0) + centres.max(axis=0))
            radius = float(np.linalg.norm(centres - middle, axis=1).max() + np.linalg.norm(grown))
            mine = near[np.linalg.norm(near - middle, axis=1) <= radius]  # this box's reach
            if len(mine) == 0:
                continue
            for k in range(steps):
                pose = samples[k][j][1]
                hits = _box_sweep_hits(mine, pose, grown, centres[k + 1] - centres[k])
                if hits.any():
                    return Hit(link, "closing", mine[int(np.argmax(hits))])
    return None


def hit_reason(hit: Hit, target: trimesh.Trimesh) -> str:
    """A refused grasp's reason: which part of the hand, when, and how far from the target the
    obstacle is."""
    _, distance, _ = trimesh.proximity.closest_point(target, hit.point[None])
    distance = float(distance[0])
    part = "the palm" if hit.link == "palm" else f"finger {hit.link[1]}"
    when = "on the way in" if hit.phase == "approach" else "while closing"
    return (f"{part} would hit an obstacle {100 * distance:.0f} cm from the target {when}")
