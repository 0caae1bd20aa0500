"""GraspIt!-style autograsp of the BarrettHand on a triangle mesh (kinematic, deterministic).

Semantics (hands/barrett/README.md, docs/design.md §7):

1. The spread is set first and never moved.
2. Approach (optional): while the open hand overlaps the object, back off along the palm's −z in
   ``approach_step`` steps; then translate along +z in ``approach_step`` steps until the hand
   touches the object (or the table), bisecting the last step to 0.01 mm, or until ``max_travel``.
3. Close: every finger DOF rises toward its maximum in ``close_step_deg`` steps (GraspIt!: 0.01
   rad), with J2 = DOF and J3 = DOF/3. After each step the moving links are checked; on a
   collision the step is bisected back to contact (to 1e-4 rad, i.e. under 0.02 mm at the
   fingertip, inside GraspIt!'s 0.1 mm). The links colliding at the end of the bisected interval
   are the ones in contact. A distal contact stops the finger. A proximal contact stops J2 only
   (breakaway): the DOF keeps rising and J3 keeps following it until the distal link touches or
   the DOF reaches its maximum. Closing ends when no finger can move.

With a support plane (``support_plane=``, or a scene built with one) the table is an obstacle
as in GraspIt!: the approach stops at the object or the table, and a link that touches the table
stops like one that touches the object (the same rules, breakaway included), so no link goes
below it. Table contacts are not grasp contacts: ``contacts`` and the quality are the object's.

The fingers do not touch each other in this model (finger–finger and finger–palm collisions are
not checked; at spread 0 fingers 1/2 pass beside finger 3), so each finger's motion depends only
on the object and the three close independently, which is the same as closing them together.

Collision queries go to :class:`grasp.collision.CollisionScene` (python-fcl): a boolean overlap test
per moving link with early exit, ~10-40 µs. Speed: a convex polytope around the object (k-DOP)
gives a lower bound d on the distance to the object (fcl GJK), and no point of a moving link
travels faster than R per unit of motion (R from the link corners), so a step of d / R is
collision-free; autograsp takes max(d / R, step) and checks the end of the step. Far from the
object that crosses free space in a few steps (about twice as fast overall), near it the GraspIt!
step applies, and every second plain step asks the polytope again (a finger sweeping past the
object leaves it behind: about 10 % fewer queries). The result does not depend on the step
size beyond the bisection tolerance unless a step jumps over an obstacle thinner than the
distance a link moves in one step (2 mm at the fingertip for the default step). Reuse one
``CollisionScene`` per mesh for many grasps.

Known simplifications: a link entirely inside a closed mesh without crossing its surface is not
in collision (triangle soup, as in GraspIt! and pybullet); there is no dynamics (see
``grasp.physics`` for a lift test).

This module must not import torch (docs/design.md §2).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import trimesh

from grasp.collision import CollisionScene, Contact, check_pose
from grasp.pinch import TABLE_PINCH, close_rising, faces_table, profile, rise
from grasp.quality import EPSILON_NO_CLOSURE, MU_RUBBER, contacts_quality
from grasp.table import SupportPlane
from grasp_client.wire import WristRise
from hands.barrett import FINGERS, JOINT_NAMES
from hands.barrett.kinematics import rotation_about

if TYPE_CHECKING:
    from grasp_client.wire import Verification

__all__ = [
    "Contact",
    "GraspResult",
    "HandDofs",
    "HandJoints",
    "autograsp",
    "joint_error_deg",
    "pregrasp_pose",
    "regrasp",
    "with_quality",
]

#: GraspIt!'s finger step: 0.01 rad.
DEFAULT_CLOSE_STEP_DEG = math.degrees(0.01)
#: GraspIt!'s approach step: 10 mm.
DEFAULT_APPROACH_STEP_M = 0.010
#: Bisection tolerances: approach (metres) and finger DOF (radians).
APPROACH_TOL_M = 1e-5
ANGLE_TOL_RAD = 1e-4
#: Among plain steps (near the bounding polytope), ask its distance again every this many: a
#: link that moved away from it (a finger sweeping past the object) takes long steps again.
_HULL_RECHECK_STEPS = 2
#: Give up backing off out of collision after this distance.
MAX_BACKOFF_M = 1.0
_NO_CONTACT = "no contact: the hand closed on nothing"
_NOT_SCORED = "quality not computed"
#: Joint-error protocol: back off this far along the approach axis before regrasping.
PREGRASP_BACKOFF_M = 0.2


class HandJoints(NamedTuple):
    """The 8 joint angles (degrees) in API order; index or access by name."""

    f1_spread: float
    f1_prox: float
    f1_dist: float
    f2_spread: float
    f2_prox: float
    f2_dist: float
    f3_prox: float
    f3_dist: float


class HandDofs(NamedTuple):
    """The 4 DOFs (degrees): spread and the three finger closing DOFs (motor angle, J2 units)."""

    spread: float
    f1: float
    f2: float
    f3: float


@dataclass(frozen=True)
class GraspResult:
    """Outcome of one autograsp. "No grasp" is a value: ``success=False`` with a ``reason``.

    Attributes
    ----------
    success : bool
        True when the grasp has force closure (epsilon > 0).
    reason : str
        Why it succeeded or failed, in words.
    palm_pose : (4, 4) float
        Final palm→world pose (after the approach), metres.
    joints_deg : HandJoints
        The 8 joint angles in degrees.
    dofs_deg : HandDofs
        Spread and the three finger DOFs in degrees.
    contacts : tuple of Contact
        Link name, world point and inward normal of each contact.
    epsilon, volume : float
        Ferrari–Canny quality of the L1 grasp wrench space (``grasp.quality``); −1 and 0 without
        force closure.
    force_epsilon : float
        The epsilon of pure forces through the centre of mass (``grasp.quality``): how well the
        grasp holds the object's weight and inertia; −1 without force closure.
    travel : float
        Net distance moved along the palm's +z during the approach (negative: backed off).
    finger_stops : tuple of 3 str
        What stopped each finger: ``"distal"`` (distal contact), ``"breakaway-distal"``
        (proximal stopped, then the distal touched), ``"breakaway-limit"`` (proximal stopped, the
        DOF reached its maximum), ``"limit"`` (touched nothing).
    approach_stop : str
        What ended the approach: ``"contact"`` (the open hand touched the object or the table),
        ``"limit"`` (it reached its planned travel untouched: a fingertip grasp whose palm stops
        above the object) or ``"none"`` (no approach). How a robot executes the grasp follows
        from it (docs/grasping.md, "Executing a grasp"): a guarded move to ``palm_pose`` that
        stops at the first touch, and for ``"contact"`` goes on until it touches.
    hold_probability : float
        On a table, the planner's estimate that the grasp holds when the object is lifted
        (:mod:`grasp.lift_model`); NaN where it was not estimated.
    verification : grasp_client.wire.Verification or None
        What lift-testing it on the planned mesh saw (``plan(..., verify=N)``, :mod:`grasp.verify`);
        None when the plan verified nothing.
    wrist_rise : grasp_client.wire.WristRise or None
        A table pinch's (:mod:`grasp.pinch`): the palm's rise along its −z against the closing
        fingers' DOF; ``palm_pose`` is where closing starts, :attr:`end_palm_pose` where it ends
        (the pose of ``joints_deg`` and ``contacts``). None for every other grasp.
    """

    success: bool
    reason: str
    palm_pose: np.ndarray
    joints_deg: HandJoints
    dofs_deg: HandDofs
    contacts: tuple[Contact, ...] = ()
    epsilon: float = EPSILON_NO_CLOSURE
    volume: float = 0.0
    travel: float = 0.0
    force_epsilon: float = EPSILON_NO_CLOSURE
    finger_stops: tuple[str, ...] = field(default=("limit", "limit", "limit"))
    approach_stop: str = "contact"
    hold_probability: float = math.nan
    verification: Verification | None = None
    wrist_rise: WristRise | None = None

    @property
    def kind(self) -> str:
        """"table pinch" (:mod:`grasp.pinch`) or "autograsp" (the palm still while closing)."""
        return "autograsp" if self.wrist_rise is None else TABLE_PINCH

    @property
    def end_palm_pose(self) -> np.ndarray:
        """(4, 4) palm→world where the fingers stopped: ``palm_pose``, or for a table pinch
        ``palm_pose`` risen by ``wrist_rise.end_m`` along its −z."""
        if self.wrist_rise is None:
            return self.palm_pose
        return _shift(np.asarray(self.palm_pose), -self.wrist_rise.end_m)

    def joint(self, name: str) -> float:
        """One joint angle (degrees) by name, e.g. ``result.joint("f3_prox")``."""
        if name not in JOINT_NAMES:
            raise ValueError(f"unknown joint {name!r}; expected one of {JOINT_NAMES}")
        return getattr(self.joints_deg, name)

    def as_dict(self) -> dict:
        """JSON-ready dictionary (lists instead of arrays)."""
        out = {
            "success": self.success,
            "reason": self.reason,
            "palm_pose": np.asarray(self.palm_pose).tolist(),
            "joints_deg": self.joints_deg._asdict(),
            "dofs_deg": self.dofs_deg._asdict(),
            "contacts": [
                {"link": c.link, "point": c.point.tolist(), "normal": c.normal.tolist()}
                for c in self.contacts
            ],
            "epsilon": self.epsilon,
            "volume": self.volume,
            "force_epsilon": self.force_epsilon,
            "travel": self.travel,
            "finger_stops": list(self.finger_stops),
            "approach_stop": self.approach_stop,
            "hold_probability": None if math.isnan(self.hold_probability)
            else self.hold_probability,
        }
        if self.verification is not None:  # only plans that verified say it
            out["verification"] = dataclasses.asdict(self.verification)
        if self.wrist_rise is not None:  # only table pinches
            out["kind"] = self.kind
            out["wrist_rise"] = dataclasses.asdict(self.wrist_rise)
            out["end_palm_pose"] = self.end_palm_pose.tolist()
        return out


# -- helpers ---------------------------------------------------------------------------------------
def _shift(pose: np.ndarray, distance: float) -> np.ndarray:
    """``pose`` moved by ``distance`` along its own +z axis."""
    out = pose.copy()
    out[:3, 3] += distance * pose[:3, 2]
    return out


def pregrasp_pose(palm_pose: np.ndarray, backoff: float = PREGRASP_BACKOFF_M) -> np.ndarray:
    """(4, 4) palm pose backed off by ``backoff`` metres along its approach axis (−z)."""
    return _shift(check_pose(palm_pose), -float(backoff))


def _scene_of(
    mesh: trimesh.Trimesh | CollisionScene, support_plane: SupportPlane | None = None
) -> CollisionScene:
    if isinstance(mesh, CollisionScene):
        return mesh if support_plane is None else mesh.with_support_plane(support_plane)
    if isinstance(mesh, trimesh.Trimesh):
        return CollisionScene(mesh, support_plane=support_plane)
    raise ValueError(f"mesh must be a trimesh.Trimesh or a CollisionScene, got {type(mesh)}")


def _speed_bounds(scene: CollisionScene, finger: str) -> tuple[float, float]:
    """Largest speed (m per rad of DOF) of any point of the finger: coupled closing, breakaway."""
    kin = scene.kinematics
    ratio = kin.params.distal_ratio
    lever = float(np.linalg.norm(kin.joint(f"{finger}_dist").origin[:3, 3]))  # J2 → J3
    prox = np.linalg.norm(scene.links[f"{finger}_prox"].corners, axis=1).max()
    dist = np.linalg.norm(scene.links[f"{finger}_dist"].corners, axis=1).max()
    # a distal point moves at most |p − J2| + ratio·|p − J3| per radian while both joints turn
    return float(max(prox, lever + dist + ratio * dist)), float(ratio * dist)


class _Search:
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


def _approach(
    search: _Search,
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
        moved = _shift(palm, t)
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
    return _shift(palm, travel), travel, bool(hit)


def _close_finger(
    search: _Search,
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
    speed_both, speed_distal = _speed_bounds(search.scene, finger)

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


def _close_pinching(
    search: _Search, palm: np.ndarray, spread: float, step: float
) -> tuple[np.ndarray, list[tuple[float, float, float, str]], WristRise]:
    """Close a table pinch (:mod:`grasp.pinch`) from ``palm``: the lock-step phase with the palm
    rising, then each finger that touched closes on from where it stopped (the palm where the
    rise ended). Returns the palm where closing ended, (DOF, J2, J3, stop) per finger (radians)
    and the rise."""
    kin = search.scene.kinematics
    params = kin.params
    ratio = params.distal_ratio
    dof_max = math.radians(params.finger_dof_max_deg)
    j2_max = math.radians(params.proximal_max_deg)
    knuckles = {f: kin.knuckle_pose(f, math.radians(spread)) for f in FINGERS}

    def poses_at(dof: float, moving: dict[str, tuple[str, float]], floor: float):
        lifted, out = _shift(palm, -max(float(rise(math.degrees(dof), params)), floor)), {}
        for f, (mode, j2) in moving.items():
            coupled = mode == "coupled"
            prox, dist = kin.finger_poses(lifted @ knuckles[f], f,
                                          min(dof, j2_max) if coupled else j2, ratio * dof)
            if coupled:  # a broken-away proximal rests on the object, only the distal closes
                out[f"{f}_prox"] = prox
            out[f"{f}_dist"] = dist
        return out

    dofs, rises = profile(params)
    slope = float(np.max(np.abs(np.diff(rises)) / np.radians(np.diff(dofs))))  # m per rad
    speed = max(_speed_bounds(search.scene, f)[0] for f in FINGERS) + slope
    stopped = close_rising(poses_at, search.first_contact, dof_max=dof_max, j2_max=j2_max,
                           step=step, speed=speed, tol=ANGLE_TOL_RAD)
    end = max(float(rise(math.degrees(q), params)) for _, q, _ in stopped.values())
    lifted = _shift(palm, -end)
    fingers = []
    for f in FINGERS:
        stop, q, j2 = stopped[f]
        if stop.endswith("distal"):  # still driven: it closes on to the object, if the palm's
            # motion took it off (the palm now still)
            frozen = j2 if stop.startswith("breakaway") else None
            fingers.append(_close_finger(search, lifted @ knuckles[f], f, step, q, frozen))
        else:
            fingers.append((q, j2, ratio * q, stop))
    wrist = WristRise(dofs.tolist(), rises.tolist(), end)
    return lifted, fingers, wrist


# -- public API ------------------------------------------------------------------------------------
def autograsp(
    mesh: trimesh.Trimesh | CollisionScene,
    palm_pose: np.ndarray,
    *,
    spread_deg: float = 0.0,
    approach: bool = True,
    max_travel: float = 0.2,
    approach_step: float = DEFAULT_APPROACH_STEP_M,
    close_step_deg: float = DEFAULT_CLOSE_STEP_DEG,
    mu: float = MU_RUBBER,
    quality: bool = True,
    support_plane: SupportPlane | None = None,
    pinch: bool = False,
) -> GraspResult:
    """Approach the object along the palm's +z and close the BarrettHand on it (GraspIt! rules).

    Parameters
    ----------
    mesh : trimesh.Trimesh or CollisionScene
        The object in world coordinates (metres). Pass a :class:`grasp.collision.CollisionScene` to
        reuse one collision model for many grasps on the same mesh.
    palm_pose : (4, 4) float
        Initial palm→world pose; +z is the approach direction.
    spread_deg : float
        Spread of fingers 1 and 2, in [0, 180] degrees; fixed during the grasp.
    approach : bool
        Back off out of collision and approach to contact first; if False close where the hand is.
    max_travel : float
        Longest approach (metres) after backing off.
    approach_step, close_step_deg : float
        Step of the approach (metres) and of the finger DOFs (degrees) before bisection.
    mu : float
        Friction coefficient for the quality measure.
    quality : bool
        Compute epsilon and volume (the 6-D hull is about half the cost of a grasp). Without it
        they are NaN and ``success`` is False; :func:`with_quality` adds them later.
    support_plane : SupportPlane or None
        The table (world frame): an obstacle for the approach and the fingers. Default: the
        scene's own (none for a mesh).
    pinch : bool
        A table pinch (:mod:`grasp.pinch`): the palm faces the table (+z along −n) and rises while
        the fingers close, keeping the tips on the table. Needs a support plane. ``max_travel``
        should end the approach where the open hand's lowest point is
        :data:`grasp.pinch.TIP_CLEARANCE_M` above the table: an approach that touches the object
        first is a failure (too tall to pinch from there).

    Returns
    -------
    GraspResult
    """
    scene = _scene_of(mesh, support_plane)
    palm = check_pose(palm_pose)
    params = scene.kinematics.params
    if not 0.0 <= spread_deg <= params.spread_max_deg:
        raise ValueError(f"spread_deg must be in [0, {params.spread_max_deg}], got {spread_deg}")
    if not (math.isfinite(max_travel) and max_travel >= 0.0):
        raise ValueError(f"max_travel must be a finite distance >= 0, got {max_travel}")
    if not approach_step > 0.0 or not close_step_deg > 0.0:
        raise ValueError("approach_step and close_step_deg must be positive")
    if pinch and (scene.support_plane is None or not faces_table(palm, scene.support_plane)):
        raise ValueError("a table pinch needs a support plane and the palm facing it "
                         "(palm +z along the plane's −n)")
    spread = math.radians(spread_deg)
    open_rad = np.radians([spread_deg, 0, 0, spread_deg, 0, 0, 0, 0])
    search = _Search(scene)

    travel, approach_stop = 0.0, "none"
    if approach:
        moved = _approach(search, palm, open_rad, max_travel=max_travel, step=approach_step)
        if moved is None:
            joints = HandJoints(*np.degrees(open_rad))
            return GraspResult(
                False,
                f"the hand is still in collision after backing off {MAX_BACKOFF_M} m",
                palm,
                joints,
                HandDofs(spread_deg, 0.0, 0.0, 0.0),
            )
        palm, travel, touched = moved
        approach_stop = "contact" if touched else "limit"
        if pinch and touched:
            return GraspResult(
                False,
                "table pinch: the open hand touched the object before its fingertips were down "
                "at the table (too tall to pinch from here)",
                palm, HandJoints(*np.degrees(open_rad)), HandDofs(spread_deg, 0.0, 0.0, 0.0),
                travel=travel, approach_stop=approach_stop,
            )

    step = math.radians(close_step_deg)
    start, wrist_rise = palm, None
    if pinch:
        palm, closed, wrist_rise = _close_pinching(search, start, spread_deg, step)
    else:
        closed = [_close_finger(search, palm @ scene.kinematics.knuckle_pose(finger, spread),
                                finger, step) for finger in FINGERS]
    dofs, joints, stops = [], {}, []
    for finger, (q, j2, j3, stop) in zip(FINGERS, closed, strict=True):
        dofs.append(math.degrees(q))
        joints[f"{finger}_prox"], joints[f"{finger}_dist"] = math.degrees(j2), math.degrees(j3)
        stops.append(stop)
    joints["f1_spread"] = joints["f2_spread"] = spread_deg
    hand_joints = HandJoints(**{name: joints[name] for name in JOINT_NAMES})

    link_poses = scene.hand_link_poses(palm, np.radians(hand_joints))
    contacts = tuple(scene.contacts(link_poses))
    reason = _NOT_SCORED if contacts else _NO_CONTACT
    if pinch and scene.colliding_links(link_poses):
        reason = "table pinch: the rising palm pulled a finger into the object (an overhang)"
    result = GraspResult(
        success=False,
        reason=reason,
        palm_pose=start,
        joints_deg=hand_joints,
        dofs_deg=HandDofs(spread_deg, *dofs),
        contacts=contacts,
        epsilon=math.nan,
        volume=math.nan,
        travel=travel,
        finger_stops=tuple(stops),
        approach_stop=approach_stop,
        wrist_rise=wrist_rise,
    )
    if reason != _NOT_SCORED and contacts:  # a failure whatever the contacts' quality
        return dataclasses.replace(result, epsilon=EPSILON_NO_CLOSURE, volume=0.0)
    return with_quality(result, scene, mu=mu) if quality else result


def with_quality(
    result: GraspResult, scene: CollisionScene, *, mu: float = MU_RUBBER
) -> GraspResult:
    """``result`` with epsilon, volume, success and reason computed from its contacts."""
    q = contacts_quality(result.contacts, center=scene.center, max_radius=scene.max_radius, mu=mu)
    if not result.contacts:
        reason = _NO_CONTACT
    elif q.force_closure:
        reason = "force closure"
    else:
        reason = f"no force closure ({len(result.contacts)} contacts)"
    return dataclasses.replace(
        result,
        success=q.force_closure,
        reason=reason,
        epsilon=q.epsilon,
        volume=q.volume,
        force_epsilon=q.force_epsilon,
    )


def regrasp(
    result: GraspResult,
    mesh: trimesh.Trimesh | CollisionScene,
    *,
    backoff: float = PREGRASP_BACKOFF_M,
    max_travel: float | None = None,
    **options,
) -> GraspResult:
    """Grasp ``mesh`` again from ``result``'s pre-grasp pose (the joint-error protocol, §7).

    The palm keeps ``result``'s orientation, approach line and spread; it is backed off by
    ``backoff`` metres along the approach axis with the hand open, then approaches (up to
    ``max_travel``, default ``backoff`` + 0.2 m) and autograsps ``mesh``. Extra keyword options go
    to :func:`autograsp`.
    """
    if not backoff >= 0.0:
        raise ValueError(f"backoff must be >= 0, got {backoff}")
    travel = backoff + 0.2 if max_travel is None else max_travel
    return autograsp(
        mesh,
        pregrasp_pose(result.palm_pose, backoff),
        spread_deg=result.dofs_deg.spread,
        approach=True,
        max_travel=travel,
        **options,
    )


def joint_error_deg(a: GraspResult, b: GraspResult) -> tuple[float, np.ndarray]:
    """Mean and per-joint absolute joint difference in degrees: (mean, (8,) per joint)."""
    per_joint = np.abs(np.asarray(a.joints_deg) - np.asarray(b.joints_deg))
    return float(per_joint.mean()), per_joint


def joints_of(results: Sequence[GraspResult]) -> np.ndarray:
    """(n, 8) joint angles in degrees of several results."""
    return np.array([r.joints_deg for r in results], dtype=np.float64).reshape(-1, 8)
