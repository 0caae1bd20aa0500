"""The lift test: execute a planned grasp on the true object, lift, shake, and judge."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from grasp.hand.autograsp import pregrasp_pose
from grasp.hand.collision import check_mesh, check_pose
from grasp.hand.quality import MU_RUBBER
from grasp.hand.result import GraspResult
from grasp.hand.table import to_upright
from grasp.physics.settings import (
    APPROACHES,
    DEFAULT_SETTINGS,
    DENSITY_KG_M3,
    GRAVITY,
    Approach,
    LiftResult,
    LiftSettings,
)
from grasp.physics.world import DynamicWorld
from grasp_client.wire import SupportPlane
from hands.barrett import BH8_282, BarrettParams
from hands.barrett.kinematics import joints_from_dofs


def _smooth(t: float) -> float:
    """Cosine ease from 0 to 1 for t in [0, 1] (zero velocity at both ends)."""
    t = min(max(t, 0.0), 1.0)
    return 0.5 - 0.5 * math.cos(math.pi * t)


def _out_and_back(t: float) -> float:
    """0 → 1 → 0 for t in [0, 1]: (1 − cos 2πt) / 2 (zero velocity at both ends)."""
    return 0.5 - 0.5 * math.cos(2.0 * math.pi * min(max(t, 0.0), 1.0))


def _schedule(
    lift: float, shake: bool, directions: np.ndarray, s: LiftSettings
) -> list[tuple[str, int, Callable[[float], np.ndarray]]]:
    """The loaded phases: (name, steps, hand offset (3,) from where the hand closed, at time t in
    the phase)."""
    up = np.array([0.0, 0.0, 1.0])
    lift_time = lift / s.lift_speed
    phases: list[tuple[str, float, Callable[[float], np.ndarray]]] = [
        ("settle", s.settle_time, lambda t: 0.0 * up),
        ("lift", lift_time, lambda t: lift * _smooth(t / lift_time) * up),
        ("lift", s.hold_time, lambda t: lift * up),
    ]
    if shake:
        period = 1.0 / s.shake_frequency
        for d in directions:
            # out and back along d: A (1 − cos 2πft) / 2, peak acceleration 2π²f²A (the cosine
            # ease would clamp at the far end: the hand stayed out and jumped back at the next
            # phase's first step, 3 cm in one time step)
            phases.append(
                (
                    "shake",
                    period,
                    lambda t, d=d: lift * up + s.shake_amplitude * _out_and_back(t / period) * d,
                )
            )
        phases.append(("shake", s.hold_time, lambda t: lift * up))
    return [(name, round(duration / s.time_step), f) for name, duration, f in phases]


def lift_test(
    mesh: trimesh.Trimesh,
    grasp: GraspResult,
    *,
    seed: int = 0,
    lift: float = 0.10,
    shake: bool = True,
    friction: float = MU_RUBBER,
    density: float = DENSITY_KG_M3,
    support_plane: SupportPlane | None = None,
    neighbours: Sequence[trimesh.Trimesh] = (),
    approach: Approach = "planned",
    settings: LiftSettings = DEFAULT_SETTINGS,
    params: BarrettParams = BH8_282,
    cache_dir: str | Path | None = None,
) -> LiftResult:
    """Execute ``grasp`` on ``mesh`` in pybullet dynamics, lift and shake; did the object stay?

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The true object in world coordinates (metres), the frame of ``grasp.palm_pose``.
    grasp : GraspResult
        A planned grasp (:func:`grasp.hand.autograsp.autograsp`, :func:`grasp.planner.plan`). Its
        palm pose and spread are used; the finger joints come from the simulated closing.
    seed : int
        Seeds the shake directions. The same inputs and seed give the same result.
    lift : float
        How far the hand rises along world +z (metres, >= 0).
    shake : bool
        Shake after the lift (``settings.shake_count`` cycles along seeded directions).
    friction : float
        Hand–object Coulomb friction μ (default 1.0, rubber; hands/barrett/README.md).
    density : float
        Object density in kg/m³ (default 500).
    support_plane : SupportPlane or None
        The table the object stands on, in the mesh's frame (n·x + d = 0, n up): gravity along
        −n from the start, the lift along +n, the table top through the object's lowest point
        (which must lie within ``settings.plane_tolerance`` of the plane: a completion cut at
        the plane rests on it, a mesh far above or through it is refused). None floats the
        object on a weak support until the hand has closed (world z up).
    neighbours : sequence of trimesh.Trimesh
        Other objects standing on the table (the mesh's frame), dynamic bodies of the same
        density; the hand touching one stops a guarded approach. The result says how far they
        moved and tilted at most over the whole test (``neighbour_moved``,
        ``neighbour_tilt_deg``).
    approach : "planned" or "guarded"
        From the pre-grasp pose (``settings.pregrasp_backoff`` behind the palm pose, hand open),
        "planned" moves the palm to ``grasp.palm_pose`` exactly (open loop); "guarded" is how a
        robot with a wrist force-torque sensor executes a plan, and what the planner plans
        (docs/grasping.md, "Executing a grasp"): toward ``grasp.palm_pose``, stopping where the
        hand first touches the object or the table; a grasp whose planned approach ended on
        touching (``grasp.approach_stop == "contact"``) goes on past the planned pose, at most
        ``settings.overtravel``, until it touches (for a grasp planned on another mesh, e.g. a
        completion, whose surface lies further than the plan's).
    settings : LiftSettings
        Time step, torque limits, speeds, shake and tolerances.
    params : BarrettParams
        Hand dimensions (the URDF is generated from them).
    cache_dir : path or None
        Cache of convex decompositions (:func:`convex_decomposition`).

    Returns
    -------
    LiftResult
        ``success``, ``displacement``, ``slip``, ``held_s`` and more. A grasp that closes on
        nothing is a failed result, not an exception.
    """
    check_mesh(mesh)
    if not isinstance(grasp, GraspResult):
        raise ValueError(f"grasp must be a GraspResult, got {type(grasp).__name__}")
    if not (math.isfinite(lift) and lift >= 0.0):
        raise ValueError(f"lift must be a finite distance >= 0 (metres), got {lift}")
    if approach not in APPROACHES:
        raise ValueError(f"approach must be one of {APPROACHES}, got {approach!r}")
    mesh, neighbours, palm = _upright(mesh, neighbours, check_pose(grasp.palm_pose),
                                      support_plane, settings)
    on_table = support_plane is not None
    directions = np.random.default_rng(seed).normal(size=(settings.shake_count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    with DynamicWorld(
        mesh,
        friction=friction,
        density=density,
        table_top=float(mesh.bounds[0, 2]) if on_table else None,
        neighbours=neighbours,
        settings=settings,
        params=params,
        cache_dir=cache_dir,
    ) as world:
        world.gravity(on_table)
        if not on_table:
            world.hold_object(settings.support_factor * world.mass * GRAVITY)
        hand = _Hand(world, grasp, palm, settings, params)
        neighbours_at = world.neighbour_poses()
        travel = hand.approach(guarded=approach == "guarded")
        closed = hand.close()
        world.hold_object(None)  # load: gravity on, support gone
        world.gravity(True)
        held = hand.lift_and_shake(_schedule(lift, shake, directions, settings), closed)
        shifted, tilted = _disturbance(neighbours_at, world.neighbour_poses())
    return _judged(held, closed, shake, world.mass, travel, shifted, tilted)


def _upright(mesh: trimesh.Trimesh, neighbours: Sequence[trimesh.Trimesh], palm: np.ndarray,
             plane: SupportPlane | None, s: LiftSettings):
    """The objects and the palm pose in the plane's upright frame (z = n·x + d; the plane z = 0
    keeps the meshes' bytes), the object checked to rest on it; unchanged without a plane."""
    if plane is None:
        return mesh, neighbours, palm
    upright = to_upright(plane)
    if not np.array_equal(upright, np.eye(4)):
        mesh = mesh.copy().apply_transform(upright)
        neighbours = [m.copy().apply_transform(upright) for m in neighbours]
        palm = upright @ palm
    gap = float(mesh.bounds[0, 2])
    if abs(gap) > s.plane_tolerance:
        where = "above" if gap > 0 else "below"
        raise ValueError(f"the object does not rest on the support plane: its lowest point "
                         f"is {100 * abs(gap):.1f} cm {where} it (at most "
                         f"{100 * s.plane_tolerance:.0f} cm); is the plane in the mesh's "
                         "frame?")
    return mesh, neighbours, palm


@dataclass
class _Closed:
    """What the closing left: the joints, the hand's rise, the contacts, each finger's stop, the
    object's pose in the palm frame then (the reference of the slip)."""

    joints_deg: np.ndarray
    rose: float
    contacts: int
    stops: tuple
    position: np.ndarray
    rotation: np.ndarray


@dataclass
class _Held:
    """What the loaded phases measured: the object's last pose in the palm frame, the largest
    slip, when (s) and in which phase it first left the hand (None: held), the time simulated."""

    position: np.ndarray
    rotation: np.ndarray
    slip: float
    left_s: float | None
    phase: str
    elapsed: float


class _Hand:
    """The hand executing one grasp in a :class:`DynamicWorld`, phase by phase: approach, close,
    then lift and shake; each step holds the spread and drives (or holds) the fingers."""

    def __init__(self, world: DynamicWorld, grasp: GraspResult, palm: np.ndarray,
                 s: LiftSettings, params: BarrettParams) -> None:
        self.world, self.grasp, self.palm, self.s = world, grasp, palm, s
        self.spread = float(grasp.dofs_deg.spread)
        # the hand as it approaches: the spread set, the fingers at their pre-shape
        opened = joints_from_dofs([self.spread, *[grasp.preshape_deg] * 3], params=params)
        self.backoff = pregrasp_pose(palm, s.pregrasp_backoff)[:3, 3] - palm[:3, 3]  # (3,)
        world.place_hand(palm, opened.tolist(), offset=self.backoff)
        self.fingers = world.controller.fingers(grasp.preshape_deg)
        self.offset = self.backoff  # the palm's offset from the planned pose (world)
        self.carriage = self.backoff  # and where it was when the fingers stopped

    def approach(self, *, guarded: bool) -> float:
        """From the pre-grasp pose, the fingers held at their pre-shape: to the planned palm
        pose (smooth start and stop), or guarded, on until the first touch (at most
        ``overtravel`` past the plan when the plan's approach ended on contact). The travel."""
        s, world, palm = self.s, self.world, self.palm
        if not guarded or self.grasp.approach_stop != "contact":
            n = max(1, math.ceil(s.pregrasp_backoff / s.approach_speed / s.time_step))
            path = [self.backoff * (1.0 - _smooth(i / n)) for i in range(1, n + 1)]
        else:  # at constant speed
            reach = s.pregrasp_backoff + s.overtravel
            n = max(1, math.ceil(reach / s.approach_speed / s.time_step))
            path = [self.backoff + reach * (i / n) * palm[:3, 2] for i in range(1, n + 1)]
        for offset in path:
            world.move_hand(offset)
            world.controller.hold_spread(self.spread)
            world.controller.hold_open(self.fingers)
            world.step()
            if guarded and world.touches():
                offset = world.hand_offset()  # stop where the hand is (it trails its target)
                world.move_hand(offset)
                break
        self.offset = self.carriage = offset
        return float(np.dot(offset - self.backoff, palm[:3, 2]))

    def close(self) -> _Closed:
        """Drive the fingers until each stops and they settle (a table pinch's palm rising with
        the closing fingers' DOF, :mod:`grasp.hand.pinch`), at most ``close_timeout``."""
        s, world = self.s, self.world
        rising, up = self.grasp.wrist_rise, -self.palm[:3, 2]
        steps, settle_left = 0, round(s.close_settle / s.time_step)
        while steps * s.time_step < s.close_timeout and settle_left > 0:
            if rising is not None:
                self.carriage = self.offset + max(rising.at(q)
                                                  for q in world.finger_dofs_deg()) * up
                world.move_hand(self.carriage)
            world.controller.hold_spread(self.spread)
            world.controller.drive(self.fingers)
            world.step()
            steps += 1
            if all(f.done for f in self.fingers):
                settle_left -= 1
        rose = float(np.dot(world.hand_offset() - self.offset, up))
        return _Closed(world.joint_values_deg(), rose, world.n_contacts(),
                       tuple(f.stop for f in self.fingers), *world.object_in_palm())

    def lift_and_shake(self, schedule, closed: _Closed) -> _Held:
        """The loaded phases of ``schedule`` (:func:`_schedule`), the hand moving from where it
        closed (a guarded approach stops short of or past the planned pose: going there first
        would push), until the object is farther than ``drop_distance`` from where it was."""
        s, world = self.s, self.world
        held = _Held(closed.position, closed.rotation, 0.0, None, "held", 0.0)
        for name, n_steps, target in schedule:
            for i in range(n_steps):
                world.move_hand(self.carriage + target((i + 1) * s.time_step))
                world.controller.hold_spread(self.spread)
                world.controller.drive(self.fingers)
                world.step()
                held.elapsed += s.time_step
                held.position, held.rotation = world.object_in_palm()
                distance = float(np.linalg.norm(held.position - closed.position))
                held.slip = max(held.slip, distance)
                if held.left_s is None and distance > s.hold_tolerance:
                    held.left_s, held.phase = held.elapsed, name
                if distance > s.drop_distance:
                    return held
        return held


def _judged(held: _Held, closed: _Closed, shake: bool, mass: float, travel: float,
            shifted: float, tilted: float) -> LiftResult:
    """The lift test's result from what its phases measured."""
    moved = held.position - closed.position
    relative = closed.rotation.T @ held.rotation
    if held.left_s is None:
        reason = "held through the lift" + (" and the shakes" if shake else "")
    elif closed.contacts == 0:
        reason = f"the hand closed on nothing; the object fell ({held.phase})"
    else:
        reason = (f"the object left the hand during {held.phase}, {held.left_s:.2f} s after "
                  "gravity came on")
    return LiftResult(
        success=held.left_s is None,
        reason=reason,
        displacement=float(np.linalg.norm(moved)),
        slip=held.slip,
        offset=moved,
        rotation_deg=math.degrees(Rotation.from_matrix(relative).magnitude()),
        held_s=held.elapsed if held.left_s is None else held.left_s,
        total_s=held.elapsed,
        phase=held.phase,
        finger_stops=closed.stops,
        joints_deg=closed.joints_deg,
        mass=mass,
        contacts=closed.contacts,
        travel=travel,
        rise=closed.rose,
        neighbour_moved=shifted,
        neighbour_tilt_deg=tilted,
    )


def _disturbance(before, after) -> tuple[float, float]:
    """The largest distance (m) a neighbour's centre of mass moved, and the largest tilt
    (degrees between a neighbour's up direction before and after: turning about the vertical
    is no tilt)."""
    shifted, tilted = 0.0, 0.0
    for (p0, r0), (p1, r1) in zip(before, after, strict=True):
        shifted = max(shifted, float(np.linalg.norm(p1 - p0)))
        up = (r1 @ r0.T)[:, 2]  # where the world's up went
        tilted = max(tilted, math.degrees(math.acos(float(np.clip(up[2], -1.0, 1.0)))))
    return shifted, tilted
