"""Every number of a lift test in one place (:class:`LiftSettings`) and its result type."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Literal, get_args

import numpy as np

#: Density of the object (kg/m³): 500, a solid between plastic ware and wood. Objects are solid, so
#: big ones are heavy (an 18 cm ball weighs 1.5 kg); pass ``density`` for lighter ones.
DENSITY_KG_M3 = 500.0
#: The object is held if its centre of mass stays this close to where it sat in the hand.
HOLD_TOLERANCE_M = 0.02
#: V-HACD settings (pybullet's defaults, written down because they are part of the cache key).
VHACD_OPTIONS = {
    "resolution": 100_000,
    "concavity": 0.0025,
    "maxNumVerticesPerCH": 64,
    "minVolumePerCH": 0.0001,
}
#: How the hand reaches the grasp pose (see :func:`lift_test`).
Approach = Literal["planned", "guarded"]
APPROACHES: tuple[str, ...] = get_args(Approach)
#: Standard gravity (m/s²), along world −z.
GRAVITY = 9.81
#: pybullet pads each convex hull of a mesh shape by this collision margin (its default, measured:
#: a hull's surface lies 1 mm outside its vertices); the pieces are shrunk by as much.
MESH_MARGIN_M = 0.001


@dataclass(frozen=True)
class LiftSettings:
    """Every number of a lift test (SI units: s, m, rad, N, N·m). See the module docstring."""

    time_step: float = 1.0 / 240.0
    solver_iterations: int = 100
    # hand carriage
    hand_force: float = 1000.0  # max force of the constraint carrying the hand (N)
    pregrasp_backoff: float = 0.05  # start this far behind the grasp pose, hand open (m)
    approach_speed: float = 0.10  # m/s
    overtravel: float = 0.05  # a guarded approach that planned to touch goes on this far (m)
    # fingers
    close_speed: float = 1.0  # finger DOF speed while closing (rad/s)
    proximal_torque: float = 4.0 / 3.0  # J2 torque limit (N·m): the J3 limit × 125 / 93.75
    distal_torque: float = 1.0  # J3 torque limit (N·m): 20 N at a 5 cm fingertip lever
    spread_torque: float = 2.0  # spread torque limit (N·m)
    position_gain: float = 0.3  # pybullet POSITION_CONTROL gains
    velocity_gain: float = 1.0
    # the worm drives do not turn back: a joint pushed open holds (hands/barrett/README.md)
    lock_slack: float = math.radians(0.5)
    lock_torque: float = 20.0  # N·m, far above what the object's weight puts on a joint
    stall_lag: float = math.radians(2.0)  # a joint this far behind its target …
    stall_speed: float = 0.1  # … and slower than this (rad/s) …
    stall_steps: int = 4  # … for this many steps in a row has stalled
    close_timeout: float = 3.5  # s; the full DOF range takes 2.4 s at 1 rad/s
    close_settle: float = 0.1  # keep squeezing this long after every finger stopped (s)
    # load
    settle_time: float = 0.25  # gravity on, hand still (s)
    lift_speed: float = 0.10  # mean lift speed (m/s); smooth (cosine) profile
    hold_time: float = 0.25  # still, after the lift and after the shakes (s)
    shake_count: int = 4
    shake_amplitude: float = 0.03  # m
    shake_frequency: float = 3.0  # Hz
    # outcome
    hold_tolerance: float = HOLD_TOLERANCE_M
    drop_distance: float = 0.05  # stop simulating once the object is this far off (m)
    table_friction: float = 0.5
    plane_tolerance: float = 0.02  # an object on a support plane rests within this of it (m)
    support_factor: float = 1.0  # without a table, a support of this × the weight holds the object

    def __post_init__(self) -> None:
        positive = ("time_step", "hand_force", "approach_speed", "close_speed", "lift_speed")
        positive += ("proximal_torque", "distal_torque", "spread_torque", "hold_tolerance")
        bad = [name for name in positive if not getattr(self, name) > 0.0]
        if bad:
            raise ValueError(f"LiftSettings: these must be positive, got {bad}")
        if self.drop_distance < self.hold_tolerance:
            raise ValueError("LiftSettings: drop_distance must be >= hold_tolerance")
        if self.solver_iterations < 1 or self.stall_steps < 1 or self.shake_count < 0:
            raise ValueError("LiftSettings: solver_iterations, stall_steps >= 1, shake_count >= 0")

    @property
    def shake_peak_accel(self) -> float:
        """Peak acceleration of a shake (m/s²): 2π²f²A for the out-and-back cosine cycle."""
        return 2.0 * math.pi**2 * self.shake_frequency**2 * self.shake_amplitude


DEFAULT_SETTINGS = LiftSettings()


@dataclass(frozen=True)
class LiftResult:
    """Outcome of one :func:`lift_test`.

    Attributes
    ----------
    success : bool
        The object's centre of mass stayed within ``hold_tolerance`` (2 cm) of where it sat in the
        hand, in the palm frame, from gravity-on through lift and shake.
    reason : str
        What happened, in words (where it was dropped, or "held").
    displacement : float
        Distance (m) of the centre of mass from where it sat in the hand, at the end of the test
        (or when the simulation stopped because the object fell ``drop_distance`` away).
    slip : float
        Largest such distance (m) seen during the test; success means ``slip <= hold_tolerance``.
    offset : (3,) float
        The final displacement as a vector in the palm frame (m).
    rotation_deg : float
        Rotation of the object relative to the palm at the end, degrees.
    held_s : float
        Simulated time (s) from gravity-on until the object first moved more than
        ``hold_tolerance``; ``total_s`` when it was held.
    total_s : float
        Simulated duration (s) of the loaded part of the test (settle, lift, shakes, holds).
    phase : str
        Where the object left the hand ("settle", "lift", "shake"), or "held".
    finger_stops : tuple of 3 str
        How each finger's closing ended: "distal" (the distal link stalled with the proximal
        moving), "breakaway-distal" (proximal stalled, then the distal), "breakaway-limit"
        (proximal stalled, the distal reached the DOF limit), "limit" (closed on nothing),
        "timeout".
    joints_deg : (8,) float
        Joint angles (degrees, :data:`hands.barrett.JOINT_NAMES` order) at the end of closing.
    mass : float
        Object mass (kg).
    contacts : int
        Hand–object contact points at the end of closing.
    travel : float
        How far (m) the palm was moved along its approach axis from the pre-grasp pose before the
        fingers closed (``pregrasp_backoff`` for the "planned" approach).
    rise : float
        How far (m) the palm rose while the fingers closed: a table pinch's (``grasp.wrist_rise``,
        followed by the fingers' DOFs), 0 for other grasps.
    neighbour_moved, neighbour_tilt_deg : float
        With neighbours on the table: how far (m) the one that moved most moved, and how far
        (degrees) the one that tilted most tilted, from the pre-grasp to the end; 0 without.
    """

    success: bool
    reason: str
    displacement: float
    slip: float
    offset: np.ndarray
    rotation_deg: float
    held_s: float
    total_s: float
    phase: str
    finger_stops: tuple[str, ...]
    joints_deg: np.ndarray
    mass: float
    contacts: int
    travel: float
    rise: float = 0.0
    neighbour_moved: float = 0.0
    neighbour_tilt_deg: float = 0.0

    def as_dict(self) -> dict:
        """JSON-ready dictionary (lists instead of arrays)."""
        out = asdict(self)
        out["offset"] = np.asarray(self.offset).tolist()
        out["joints_deg"] = np.asarray(self.joints_deg).tolist()
        out["finger_stops"] = list(self.finger_stops)
        return out
