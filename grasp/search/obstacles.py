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
its centre (conservative by at most that much). Every test is one ball query of the voxels' tree
for all the boxes' swept spheres, then the exact slab test of the pairs it returns
(:func:`_sweeps`); :func:`hand_clear` checks many pre-grasps at once that way. A grasp whose
hand reaches an obstacle is refused by the planner with the reason (:func:`hit_reason`). The
lift that follows is not checked: it moves the hand away from the table, away from neighbours
standing on it.

This module must not import torch (docs/design.md §2).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from completion.grid import OBSTACLE_PITCH_M, voxel_keys
from grasp_client.wire import SupportPlane
from hands.barrett import BH8_282, FINGERS, LINK_NAMES, BarrettParams, HandKinematics
from hands.barrett.kinematics import joints_from_dofs

__all__ = ["CLOSING_STEP_DEG", "DEFAULT_PITCH_M", "Hit", "Obstacles", "hand_clear", "hit_reason",
           "seen_others", "sweep_hit"]

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


def seen_others(others: np.ndarray, target: np.ndarray, plane: SupportPlane) -> np.ndarray:
    """Which of a view's other points (not the target's, world frame, (m, 3)) are obstacles:
    above the table ``plane`` (world frame) by :data:`ABOVE_TABLE_M`, within
    :data:`REACH_M` of the target's points ``target`` ((n, 3), world) along the table, and not
    within :data:`TARGET_MARGIN_M` of them. One rule for the service's views and the
    evaluation's (:func:`grasp.evaluate.clutter_scenes.seen_obstacles`)."""
    others = np.asarray(others, dtype=np.float64).reshape(-1, 3)
    target = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    if len(others) == 0 or len(target) == 0:
        return others[:0]
    others = others[plane.height(others) > ABOVE_TABLE_M]
    if len(others) == 0:
        return others

    def flat(p: np.ndarray) -> np.ndarray:  # projected onto the table
        return p - np.outer(plane.height(p), plane.normal)

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


def _box_sweep_hits(points: np.ndarray, poses: np.ndarray, halves: np.ndarray,
                    moves: np.ndarray) -> np.ndarray:
    """(P,) bool: whether each box (``poses`` (P, 4, 4) box→world, ``halves`` (P, 3) half
    extents) reaches its point of (P, 3) ``points`` while it translates by its (P, 3) ``moves``
    (world): the slab intervals of the motion parameter s in [0, 1] overlap."""
    rot = poses[:, :3, :3]
    q = np.einsum("pi,pij->pj", points - poses[:, :3, 3], rot)  # the points in the box frames
    u = np.einsum("pij,pi->pj", rot, moves)
    still = np.abs(u) < 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = (q - halves) / u, (q + halves) / u
    lo = np.where(still, np.where(np.abs(q) <= halves, 0.0, 2.0), np.minimum(a, b))
    hi = np.where(still, 1.0, np.maximum(a, b))
    return np.maximum(lo.max(axis=1), 0.0) <= np.minimum(hi.min(axis=1), 1.0)


def _sweeps(obstacles: Obstacles, poses: np.ndarray, halves: np.ndarray, moves: np.ndarray):
    """Every (box, voxel) pair where one of (B, 4, 4) boxes (``halves`` (B, 3), grown by the
    voxels' :attr:`~Obstacles.reach`), translating by its (B, 3) move, reaches the voxel's
    centre: (box indices, voxel indices), ordered by box, then voxel. One ball query of the
    voxel tree for all the boxes' swept spheres, then the exact test of those pairs."""
    halves = halves + obstacles.reach
    centres = poses[:, :3, 3] + 0.5 * moves
    radius = np.linalg.norm(halves, axis=1) + 0.5 * np.linalg.norm(moves, axis=1)
    lists = obstacles._tree.query_ball_point(centres, radius, return_sorted=True)
    counts = np.fromiter((len(x) for x in lists), dtype=np.intp, count=len(lists))
    if not counts.sum():
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    box = np.repeat(np.arange(len(poses)), counts)
    voxel = np.concatenate([x for x in lists if x]).astype(np.intp)
    hit = _box_sweep_hits(obstacles.centres[voxel], poses[box], halves[box], moves[box])
    return box[hit], voxel[hit]


#: The links that turn while the fingers close, and each finger's (J2, J3) in the 8 joints.
FINGER_LINKS = ("_prox", "_dist")
_FINGER_JOINTS = ((1, 2), (4, 5), (6, 7))


class _Hand:
    """The hand's links as boxes (each primitive's bounding box) for obstacle tests."""

    def __init__(self, params: BarrettParams) -> None:
        self.kinematics = HandKinematics(params)
        self.boxes = {link: [(prim.pose, prim.half_extents())
                             for prim in self.kinematics.primitives_of(link)]
                      for link in LINK_NAMES}

    def world_boxes(self, palm: np.ndarray, joints_rad: np.ndarray):
        """Every primitive's box at these joints: (links, (B, 4, 4) box→world, (B, 3) half
        extents); ``palm`` (4, 4) or (k, 4, 4), the boxes then (k, B, 4, 4)."""
        poses = self.kinematics.link_poses(joints_rad)
        links = [link for link in poses for _ in self.boxes[link]]
        local = np.stack([poses[link] @ pose for link in poses for pose, _ in self.boxes[link]])
        halves = np.stack([half for link in poses for _, half in self.boxes[link]])
        return links, np.asarray(palm)[..., None, :, :] @ local, halves


@functools.lru_cache(maxsize=4)
def _hand(params: BarrettParams) -> _Hand:
    return _Hand(params)


def _first_hit(obstacles: Obstacles, links: Sequence[str], poses: np.ndarray,
               halves: np.ndarray, move: np.ndarray, phase: str) -> Hit | None:
    """The first of the boxes (``links``, (B, 4, 4) ``poses``, (B, 3) ``halves``) that reaches a
    voxel while translating by ``move``."""
    box, voxel = _sweeps(obstacles, poses, halves, np.broadcast_to(move, (len(poses), 3)))
    if len(box) == 0:
        return None
    return Hit(links[box[0]], phase, obstacles.centres[voxel[0]])


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
    hit = _first_hit(obstacles, *hand.world_boxes(start, opened), stop[:3, 3] - start[:3, 3],
                     "approach")
    if hit is not None:
        return hit
    if np.allclose(closed, opened) and np.allclose(end, stop):
        return None  # nothing moves after the approach
    # the palm and the knuckles (the spread is set) move only with a pinch's rise: swept along it
    links, poses, halves = hand.world_boxes(stop, opened)
    fixed = [i for i, link in enumerate(links) if not link.endswith(FINGER_LINKS)]
    hit = _first_hit(obstacles, [links[i] for i in fixed], poses[fixed], halves[fixed],
                     end[:3, 3] - stop[:3, 3], "closing")
    if hit is not None:
        return hit
    travel = float(np.max(np.abs(np.degrees(closed - opened))))
    steps = max(1, math.ceil(travel / CLOSING_STEP_DEG))
    # between two samples each finger link's box is swept along its centre's motion and grown
    # by what its turn adds: a link turns by at most its joints' change (the distal's
    # orientation is J2 + J3), its corners by its half diagonal times that
    turn = 2.0 * math.radians(travel) / steps
    s = np.linspace(0.0, 1.0, steps + 1)
    palms = np.tile(stop, (steps + 1, 1, 1))  # a pinch's palm rises while the fingers close
    palms[:, :3, 3] = (1.0 - s)[:, None] * stop[:3, 3] + s[:, None] * end[:3, 3]
    links, poses, halves = [], [], []  # every finger box's steps, in order
    for finger, (i2, i3) in zip(FINGERS, _FINGER_JOINTS, strict=True):
        knuckle = hand.kinematics.knuckle_pose(finger, float(closed[0]))
        paths = hand.kinematics.finger_path(palms @ knuckle, finger,
                                            (1 - s) * opened[i2] + s * closed[i2],
                                            (1 - s) * opened[i3] + s * closed[i3])
        for link, path in zip((f"{finger}_prox", f"{finger}_dist"), paths, strict=True):
            for local, half in hand.boxes[link]:
                links.append(link)
                poses.append(path @ local)  # (steps + 1, 4, 4)
                halves.append(half + float(np.linalg.norm(half)) * turn)
    poses = np.stack(poses)
    moves = np.diff(poses[:, :, :3, 3], axis=1)  # (boxes, steps, 3)
    box, voxel = _sweeps(obstacles, poses[:, :-1].reshape(-1, 4, 4),
                         np.repeat(np.stack(halves), steps, axis=0), moves.reshape(-1, 3))
    if len(box) == 0:
        return None
    return Hit(links[box[0] // steps], "closing", obstacles.centres[voxel[0]])


def hand_clear(obstacles: Obstacles | None, palms: np.ndarray, spreads_deg: np.ndarray,
               preshape_deg: float = 0.0, params: BarrettParams = BH8_282) -> np.ndarray:
    """(k,) bool: whether the hand standing still at each of (k, 4, 4) palm poses, at (k,)
    spreads and its fingers at ``preshape_deg``, reaches no obstacle (:func:`sweep_hit` of a
    hand that does not move, for many poses at once)."""
    palms = np.asarray(palms, dtype=np.float64).reshape(-1, 4, 4)
    spreads = np.asarray(spreads_deg, dtype=np.float64).reshape(-1)
    clear = np.ones(len(palms), dtype=bool)
    if obstacles is None or len(obstacles) == 0 or len(palms) == 0:
        return clear
    hand = _hand(params)
    for spread in np.unique(spreads):
        which = np.flatnonzero(spreads == spread)
        joints = np.radians(joints_from_dofs([spread, *[preshape_deg] * 3], params=params))
        _, poses, halves = hand.world_boxes(palms[which], joints)  # (k, B, 4, 4)
        count = halves.shape[0]
        box, _ = _sweeps(obstacles, poses.reshape(-1, 4, 4), np.tile(halves, (len(which), 1)),
                         np.zeros((len(which) * count, 3)))
        clear[which[np.unique(box // count)]] = False
    return clear


def hit_reason(hit: Hit, target: trimesh.Trimesh) -> str:
    """A refused grasp's reason: which part of the hand, when, and how far from the target the
    obstacle is."""
    _, distance, _ = trimesh.proximity.closest_point(target, hit.point[None])
    distance = float(distance[0])
    part = "the palm" if hit.link == "palm" else f"finger {hit.link[1]}"
    when = "on the way in" if hit.phase == "approach" else "while closing"
    return (f"{part} would hit an obstacle {100 * distance:.0f} cm from the target {when}")
