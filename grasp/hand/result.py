"""What an autograsp returns: :class:`GraspResult` (a value, also when there is no grasp), the
hand's joints and DOFs, and the joint error between two results (docs/design.md §7)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from grasp.hand.closing import shift
from grasp.hand.collision import Contact
from grasp.hand.pinch import TABLE_PINCH
from grasp.hand.quality import EPSILON_NO_CLOSURE
from hands.barrett import JOINT_NAMES

if TYPE_CHECKING:
    from grasp_client.wire import Verification, WristRise


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
        Ferrari–Canny quality of the L1 grasp wrench space (``grasp.hand.quality``); −1 and 0
        without force closure.
    force_epsilon : float
        The epsilon of pure forces through the centre of mass (``grasp.hand.quality``): how well the
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
        (:mod:`grasp.ranking.lift_model`); NaN where it was not estimated.
    verification : grasp_client.wire.Verification or None
        What lift-testing it on the planned mesh saw (``plan(..., verify=N)``,
        :mod:`grasp.physics.verify`); None when the plan verified nothing.
    wrist_rise : grasp_client.wire.WristRise or None
        A table pinch's (:mod:`grasp.hand.pinch`): the palm's rise along its −z against the closing
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
        """"table pinch" (:mod:`grasp.hand.pinch`) or "autograsp" (the palm still while closing)."""
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


def joint_error_deg(a: GraspResult, b: GraspResult) -> tuple[float, np.ndarray]:
    """Mean and per-joint absolute joint difference in degrees: (mean, (8,) per joint)."""
    per_joint = np.abs(np.asarray(a.joints_deg) - np.asarray(b.joints_deg))
    return float(per_joint.mean()), per_joint


def joints_of(results: Sequence[GraspResult]) -> np.ndarray:
    """(n, 8) joint angles in degrees of several results."""
    return np.array([r.joints_deg for r in results], dtype=np.float64).reshape(-1, 8)
