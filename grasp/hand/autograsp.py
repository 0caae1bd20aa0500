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

The stepping search, the approach and a finger's closing live in :mod:`grasp.hand.closing`; the
table pinch's closing in :mod:`grasp.hand.pinch`. Collision queries go to
:class:`grasp.hand.collision.CollisionScene` (python-fcl): a boolean overlap test
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
from typing import TYPE_CHECKING

import numpy as np
import trimesh

from grasp.hand.closing import MAX_BACKOFF_M, Search, approach_until_contact, close_finger, shift
from grasp.hand.collision import CollisionScene, Contact, check_pose
from grasp.hand.pinch import close_pinching, faces_table
from grasp.hand.quality import EPSILON_NO_CLOSURE, MU_RUBBER, contacts_quality
from grasp.hand.result import GraspResult, HandDofs, HandJoints
from grasp_client.wire import SupportPlane
from hands.barrett import FINGERS, JOINT_NAMES
from hands.barrett.kinematics import joints_from_dofs

if TYPE_CHECKING:
    pass

__all__ = [
    "Contact",
    "autograsp",
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


def _check_options(scene: CollisionScene, palm: np.ndarray, spread_deg: float, max_travel: float,
                   approach_step: float, close_step_deg: float, pinch: bool,
                   preshape_deg: float) -> None:
    """:func:`autograsp`'s options, each a ValueError saying what was expected."""
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
        The object in world coordinates (metres). Pass a
        :class:`grasp.hand.collision.CollisionScene` to reuse one collision model for many grasps on
        the same mesh.
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
        A table pinch (:mod:`grasp.hand.pinch`): the palm faces the table (+z along −n) and rises
        while the fingers close, keeping the tips on the table. Needs a support plane.
        ``max_travel`` should end the approach where the open hand's lowest point is
        :data:`grasp.hand.pinch.TIP_CLEARANCE_M` above the table: an approach that touches the
        object first is a failure (too tall to pinch from there).
    preshape_deg : float
        The fingers' DOF while the hand approaches (0: open), from which they close: a hand
        pre-shaped among other objects (:mod:`grasp.search.obstacles`) is narrower than the open
        one, whose fingertips reach 16 cm from the palm's axis.

    Returns
    -------
    GraspResult
    """
    scene = _scene_of(mesh, support_plane)
    palm = check_pose(palm_pose)
    params = scene.kinematics.params
    _check_options(scene, palm, spread_deg, max_travel, approach_step, close_step_deg, pinch,
                   preshape_deg)
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
