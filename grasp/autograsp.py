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

The stepping search, the approach and a finger's closing live in :mod:`grasp.closing`; the table
pinch's closing in :mod:`grasp.pinch`. Collision queries go to
:class:`grasp.collision.CollisionScene` (python-fcl): a boolean overlap test
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
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import trimesh

from grasp.closing import MAX_BACKOFF_M, Search, approach_until_contact, close_finger, shift
from grasp.collision import CollisionScene, Contact, check_pose
from grasp.pinch import TABLE_PINCH, close_pinching, faces_table
from grasp.quality import EPSILON_NO_CLOSURE, MU_RUBBER, contacts_quality
from grasp_client.wire import SupportPlane
from hands.barrett import FINGERS, JOINT_NAMES
from hands.barrett.kinematics import joints_from_dofs

if TYPE_CHECKING:
    from grasp_client.wire import Verification, WristRise

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
    preshape_deg : float
        The fingers' DOF while the hand approached, from which they closed (0: open).
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
    preshape_deg: float = 0.0

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
        return shift(np.asarray(self.palm_pose), -self.wrist_rise.end_m)

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
        if self.preshape_deg:  # only pre-shaped grasps
            out["preshape_deg"] = self.preshape_deg
        if self.wrist_rise is not None:  # only table pinches
            out["kind"] = self.kind
            out["wrist_rise"] = dataclasses.asdict(self.wrist_rise)
            out["end_palm_pose"] = self.end_palm_pose.tolist()
        return out


# -- helpers ---------------------------------------------------------------------------------------
def pregrasp_pose(palm_pose: np.ndarray, backoff: float = PREGRASP_BACKOFF_M) -> np.ndarray:
    """(4, 4) palm pose backed off by ``backoff`` metres along its approach axis (−z)."""
    return shift(check_pose(palm_pose), -float(backoff))


def _scene_of(
    mesh: trimesh.Trimesh | CollisionScene, support_plane: SupportPlane | None = None
) -> CollisionScene:
    if isinstance(mesh, CollisionScene):
        return mesh if support_plane is None else mesh.with_support_plane(support_plane)
    if isinstance(mesh, trimesh.Trimesh):
        return CollisionScene(mesh, support_plane=support_plane)
    raise ValueError(f"mesh must be a trimesh.Trimesh or a CollisionScene, got {type(mesh)}")


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
    preshape_deg: float = 0.0,
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
    preshape_deg : float
        The fingers' DOF while the hand approaches (0: open), from which they close: a hand
        pre-shaped among other objects (:mod:`grasp.obstacles`) is narrower than the open one,
        whose fingertips reach 16 cm from the palm's axis.

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
    if not 0.0 <= preshape_deg < params.finger_dof_max_deg or (pinch and preshape_deg):
        raise ValueError(f"preshape_deg must be in [0, {params.finger_dof_max_deg}) degrees "
                         f"(0 for a table pinch), got {preshape_deg}")
    spread = math.radians(spread_deg)
    open_rad = np.radians(joints_from_dofs([spread_deg, *[preshape_deg] * 3], params=params))
    preshape = math.radians(preshape_deg)
    search = Search(scene)

    travel, approach_stop = 0.0, "none"
    if approach:
        moved = approach_until_contact(search, palm, open_rad, max_travel=max_travel,
                                       step=approach_step)
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
        palm, closed, wrist_rise = close_pinching(search, start, spread_deg, step)
    else:
        closed = [close_finger(search, palm @ scene.kinematics.knuckle_pose(finger, spread),
                                finger, step, start=preshape) for finger in FINGERS]
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
        preshape_deg=float(preshape_deg),
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
