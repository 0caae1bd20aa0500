"""The search under the autograsp (:mod:`grasp.hand.autograsp`, :mod:`grasp.hand.pinch`): where
moving links first touch the object or the table along a 1-D motion, the approach along the palm's
+z, and one finger's closing by the Barrett rules (coupled, then breakaway).

:class:`Search` steps a motion parameter and bisects the last step to the first contact; a
convex polytope around the object bounds the distance to it, so far from it the steps are as long
as no link can reach it (:mod:`grasp.hand.autograsp` explains the speed-up and the tolerances).

This module must not import torch (docs/design.md §2).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from grasp.hand.collision import CollisionScene
from hands.barrett.kinematics import rotation_about

#: Bisection tolerances: approach (metres) and finger DOF (radians).
APPROACH_TOL_M = 1e-5
ANGLE_TOL_RAD = 1e-4
#: Among plain steps (near the bounding polytope), ask its distance again every this many: a
#: link that moved away from it (a finger sweeping past the object) takes long steps again.
_HULL_RECHECK_STEPS = 2
#: Give up backing off out of collision after this distance.
MAX_BACKOFF_M = 1.0


def shift(pose: np.ndarray, distance: float) -> np.ndarray:
    """``pose`` moved by ``distance`` along its own +z axis."""
    out = pose.copy()
    out[:3, 3] += distance * pose[:3, 2]
    return out


def speed_bounds(scene: CollisionScene, finger: str) -> tuple[float, float]:
    """Largest speed (m per rad of DOF) of any point of the finger: coupled closing, breakaway."""
    kin = scene.kinematics
    ratio = kin.params.distal_ratio
    lever = float(np.linalg.norm(kin.joint(f"{finger}_dist").origin[:3, 3]))  # J2 → J3
    prox = np.linalg.norm(scene.links[f"{finger}_prox"].corners, axis=1).max()
    dist = np.linalg.norm(scene.links[f"{finger}_dist"].corners, axis=1).max()
    # a distal point moves at most |p − J2| + ratio·|p − J3| per radian while both joints turn
    return float(max(prox, lever + dist + ratio * dist)), float(ratio * dist)


class Search:
    """First contact of some moving links along a 1-D motion parameter (stepping + bisection)."""

    def __init__(self, scene: CollisionScene) -> None:
        self.scene = scene
        self._last_hit: str | None = None  # checked first: it decides most bisection queries

    def collides(self, poses: dict[str, np.ndarray]) -> bool:
        last = self._last_hit
        if last in poses and self.scene.link_collides(last, poses[last]):
            return True
        for link, pose in poses.items():
            if link != last and self.scene.link_collides(link, pose):
                self._last_hit = link
                return True
        return False

    def free_distance(self, poses: dict[str, np.ndarray]) -> float:
        return min(self.scene.hull_distance(link, pose) for link, pose in poses.items())

    def first_contact(
        self,
        poses_at: Callable[[float], dict[str, np.ndarray]],
        start: float,
        stop: float,
        *,
        step: float,
        speed: float,
        tol: float,
    ) -> tuple[float, list[str]]:
        """Largest free parameter before the first collision in [start, stop], and the links hit.

        ``speed`` bounds how far (metres) any point of the moving links travels per unit of the
        parameter. The links hit are those overlapping the object at the end of the bisected
        interval. Returns (stop, []) when nothing is hit.
        """
        poses = poses_at(start)
        if self.collides(poses):
            return start, self.scene.colliding_links(poses)
        lo, use_hull, plain = start, True, 0
        while lo < stop:
            jump = 0.0
            if use_hull or plain >= _HULL_RECHECK_STEPS:
                # a step of d / speed cannot reach the bounding polytope, hence not the object
                jump = self.free_distance(poses) / speed
                use_hull = jump > step  # close to the object: plain steps, checked now and then
                plain = 0
            plain += jump <= step
            hi = min(lo + max(step, jump), stop)
            poses = poses_at(hi)
            if not self.collides(poses):
                lo = hi
                continue
            while hi - lo > tol:
                mid = 0.5 * (lo + hi)
                mid_poses = poses_at(mid)
                if self.collides(mid_poses):
                    hi, poses = mid, mid_poses
                else:
                    lo = mid
            return lo, self.scene.colliding_links(poses)
        return stop, []


def approach_until_contact(
    search: Search,
    palm: np.ndarray,
    joints_rad: np.ndarray,
    *,
    max_travel: float,
    step: float,
) -> tuple[np.ndarray, float, bool] | None:
    """Back off out of collision, then move along +z to the first contact: the palm pose, the
    travel and whether it touched. None if stuck."""
    scene = search.scene
    local = scene.kinematics.link_poses(joints_rad)

    def poses_at(t: float) -> dict[str, np.ndarray]:
        moved = shift(palm, t)
        return {link: moved @ pose for link, pose in local.items()}

    back = 0.0
    while search.collides(poses_at(-back)):
        back += step
        if back > MAX_BACKOFF_M:
            return None
    start = -back
    travel, hit = search.first_contact(
        poses_at, start, start + max_travel, step=step, speed=1.0, tol=APPROACH_TOL_M
    )
    return shift(palm, travel), travel, bool(hit)


def close_finger(
    search: Search,
    knuckle: np.ndarray,
    finger: str,
    step: float,
    start: float = 0.0,
    frozen_j2: float | None = None,
) -> tuple[float, float, float, str]:
    """Close one finger from DOF ``start`` (radians; open by default), its J2 stopped at
    ``frozen_j2`` when it broke away already. Returns (DOF, J2, J3) in radians and what stopped
    it."""
    kin = search.scene.kinematics
    params = kin.params
    ratio = params.distal_ratio
    dof_max = math.radians(params.finger_dof_max_deg)
    j2_max = math.radians(params.proximal_max_deg)
    prox_name, dist_name = f"{finger}_prox", f"{finger}_dist"
    speed_both, speed_distal = speed_bounds(search.scene, finger)

    def coupled(q: float) -> dict[str, np.ndarray]:
        prox, dist = kin.finger_poses(knuckle, finger, min(q, j2_max), ratio * q)
        return {prox_name: prox, dist_name: dist}

    if frozen_j2 is None:
        q, hit = search.first_contact(
            coupled, start, dof_max, step=step, speed=speed_both, tol=ANGLE_TOL_RAD
        )
        if not hit:
            return q, min(q, j2_max), ratio * q, "limit"
        if dist_name in hit:
            return q, min(q, j2_max), ratio * q, "distal"
        j2 = min(q, j2_max)
    else:
        q, j2 = start, frozen_j2
    # breakaway: J2 frozen, the DOF keeps rising and J3 follows it
    prox_pose, _ = kin.finger_poses(knuckle, finger, j2, 0.0)
    j3_frame = prox_pose @ kin.joint(dist_name).origin
    turn = rotation_about(kin.joint(dist_name).axis)

    def distal_only(dof: float) -> dict[str, np.ndarray]:
        return {dist_name: j3_frame @ turn(ratio * dof)}

    q2, hit2 = search.first_contact(
        distal_only, q, dof_max, step=step, speed=speed_distal, tol=ANGLE_TOL_RAD
    )
    return q2, j2, ratio * q2, "breakaway-distal" if hit2 else "breakaway-limit"
