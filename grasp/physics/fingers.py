"""The Barrett closing controller of the lift test's hand: coupling, breakaway and the worm
drives' hold, one control step at a time (docs/design.md §7; the numbers in
:class:`grasp.physics.settings.LiftSettings`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

from completion.bullet import pybullet
from grasp.physics.hand import JointInfo
from grasp.physics.settings import LiftSettings
from hands.barrett import FINGERS, BarrettParams


@dataclass
class Finger:
    """Closing state of one finger (radians)."""

    prox: int  # pybullet joint indices
    dist: int
    dof: float = 0.0  # commanded DOF (motor angle in J2 units)
    mode: str = "coupled"  # coupled → breakaway → stopped; coupled → stopped; coupled → limit
    stop: str = "timeout"
    prox_count: int = 0  # consecutive stalled steps
    dist_count: int = 0
    peak: list = field(default_factory=lambda: [0.0, 0.0])  # most closed J2, J3 so far

    @property
    def done(self) -> bool:
        return self.mode in ("stopped", "limit")


class FingerController:
    """Drives the spread and finger joints of the hand ``hand_id`` in ``client`` (``joints``: by
    name, :func:`grasp.physics.hand.load_hand`) under ``settings``' torque limits and gains."""

    def __init__(self, client, hand_id: int, joints: dict[str, JointInfo],
                 settings: LiftSettings, params: BarrettParams) -> None:
        self.client, self.hand_id, self.joints = client, hand_id, joints
        self.settings, self.params = settings, params

    def hold_spread(self, spread_deg: float) -> None:
        """Position-control both spread joints at ``spread_deg`` with the spread torque limit."""
        for name in ("f1_spread", "f2_spread"):
            self._position(
                self.joints[name].index, math.radians(spread_deg), self.settings.spread_torque
            )

    def fingers(self, preshape_deg: float = 0.0) -> list[Finger]:
        """Fresh closing state of the three fingers, at DOF ``preshape_deg`` (0: open)."""
        dof = math.radians(preshape_deg)
        return [
            Finger(self.joints[f"{f}_prox"].index, self.joints[f"{f}_dist"].index, dof=dof)
            for f in FINGERS
        ]

    def hold_open(self, fingers: Sequence[Finger]) -> None:
        """Position-control every finger joint where its DOF puts it before closing (J2 = DOF,
        J3 = DOF × the distal ratio; 0: open)."""
        s, p = self.settings, self.params
        for finger in fingers:
            j2 = min(finger.dof, math.radians(p.proximal_max_deg))
            self._position(finger.prox, j2, s.proximal_torque)
            self._position(finger.dist, finger.dof * p.distal_ratio, s.distal_torque)

    def drive(self, fingers: Sequence[Finger]) -> None:
        """One control step of every finger: Barrett coupling and breakaway.

        Coupled, the DOF rises at ``close_speed`` and J2 = DOF, J3 = DOF/3 under position control.
        The controller watches the joints: a joint more than ``stall_lag`` behind its target and
        slower than ``stall_speed`` for ``stall_steps`` steps has stalled. A stalled proximal whose
        distal still moves breaks away: J2 then presses with its torque limit and the distal
        target keeps following DOF/3. A stalled distal stops the finger: both joints press with
        their limits. A finger whose DOF reaches its maximum untouched holds there ("limit").

        Neither joint opens under load: both are driven through single-start worms into worm
        gears (Barrett's BH8-280 drivetrain, hands/barrett/README.md), which the object cannot
        turn back. A joint pushed more than ``lock_slack`` open from the most closed angle it
        reached is held there with ``lock_torque``.
        """
        s, c = self.settings, self.client
        ratio = self.params.distal_ratio
        dof_max = math.radians(self.params.finger_dof_max_deg)
        j2_max = math.radians(self.params.proximal_max_deg)
        for finger in fingers:
            (q2, v2, *_), (q3, v3, *_) = c.getJointStates(self.hand_id, [finger.prox, finger.dist])
            if finger.mode in ("coupled", "breakaway"):
                if finger.mode == "coupled":
                    stalled = min(finger.dof, j2_max) - q2 > s.stall_lag and v2 < s.stall_speed
                    finger.prox_count = finger.prox_count + 1 if stalled else 0
                stalled = ratio * finger.dof - q3 > s.stall_lag and v3 < ratio * s.stall_speed
                finger.dist_count = finger.dist_count + 1 if stalled else 0
                if finger.dist_count >= s.stall_steps:
                    finger.stop = "distal" if finger.mode == "coupled" else "breakaway-distal"
                    finger.mode = "stopped"
                elif finger.mode == "coupled" and finger.prox_count >= s.stall_steps:
                    if v3 < ratio * s.stall_speed:  # the distal is blocked too
                        finger.stop, finger.mode = "distal", "stopped"
                    else:
                        finger.mode = "breakaway"
                elif finger.dof >= dof_max:
                    finger.stop = "limit" if finger.mode == "coupled" else "breakaway-limit"
                    finger.mode = "limit" if finger.mode == "coupled" else "stopped"
                else:
                    finger.dof = min(finger.dof + s.close_speed * s.time_step, dof_max)
            if finger.mode in ("coupled", "limit"):
                self._position(finger.prox, min(finger.dof, j2_max), s.proximal_torque)
            else:
                self._press(finger.prox, s.proximal_torque)
            if finger.mode == "stopped" and finger.stop != "breakaway-limit":
                self._press(finger.dist, s.distal_torque)
            else:
                self._position(finger.dist, ratio * finger.dof, s.distal_torque)
            for k, (joint, q) in enumerate(((finger.prox, q2), (finger.dist, q3))):
                finger.peak[k] = max(finger.peak[k], q)
                if q < finger.peak[k] - s.lock_slack:  # back-driven: the worm holds it
                    self._position(joint, finger.peak[k], s.lock_torque)

    def _position(self, joint: int, target: float, torque: float) -> None:
        self.client.setJointMotorControl2(
            self.hand_id,
            joint,
            pybullet.POSITION_CONTROL,
            targetPosition=target,
            force=torque,
            positionGain=self.settings.position_gain,
            velocityGain=self.settings.velocity_gain,
        )

    def _press(self, joint: int, torque: float) -> None:
        # a velocity motor that cannot reach its target speed applies its full torque
        self.client.setJointMotorControl2(
            self.hand_id,
            joint,
            pybullet.VELOCITY_CONTROL,
            targetVelocity=self.settings.close_speed,
            force=torque,
        )
