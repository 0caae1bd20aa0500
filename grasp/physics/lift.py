"""The lift test: execute a planned grasp on the true object, lift, shake, and judge."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from grasp.autograsp import GraspResult, pregrasp_pose
from grasp.collision import check_mesh, check_pose
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
from grasp.quality import MU_RUBBER
from grasp.table import SupportPlane, to_upright
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
        A planned grasp (:func:`grasp.autograsp.autograsp`, :func:`grasp.planner.plan`). Its palm
        pose and spread are used; the finger joints come from the simulated closing.
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
    s = settings
    palm = check_pose(grasp.palm_pose)
    if support_plane is not None:  # simulate in the plane's upright frame (z = n·x + d)
        upright = to_upright(support_plane)
        if not np.array_equal(upright, np.eye(4)):  # the plane z = 0 keeps the mesh's bytes
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
    table = support_plane is not None
    directions = np.random.default_rng(seed).normal(size=(s.shake_count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    spread = float(grasp.dofs_deg.spread)
    # the hand as it approaches: the spread set, the fingers at their pre-shape
    open_joints = joints_from_dofs([spread, *[grasp.preshape_deg] * 3], params=params).tolist()
    backoff = pregrasp_pose(palm, s.pregrasp_backoff)[:3, 3] - palm[:3, 3]  # (3,) world

    with DynamicWorld(
        mesh,
        friction=friction,
        density=density,
        table_top=float(mesh.bounds[0, 2]) if table else None,
        neighbours=neighbours,
        settings=s,
        params=params,
        cache_dir=cache_dir,
    ) as world:
        world.gravity(table)
        if not table:
            world.hold_object(s.support_factor * world.mass * GRAVITY)
        world.place_hand(palm, open_joints, offset=backoff)
        fingers = world.fingers(grasp.preshape_deg)
        neighbours_at = world.neighbour_poses()
        # approach from the pre-grasp pose, hand open
        guarded = approach == "guarded"
        if not guarded or grasp.approach_stop != "contact":
            # to the planned palm pose, smooth start and stop
            n = max(1, math.ceil(s.pregrasp_backoff / s.approach_speed / s.time_step))
            path = [backoff * (1.0 - _smooth(i / n)) for i in range(1, n + 1)]
        else:  # on until the first touch, at constant speed, at most overtravel past the plan
            reach = s.pregrasp_backoff + s.overtravel
            n = max(1, math.ceil(reach / s.approach_speed / s.time_step))
            path = [backoff + reach * (i / n) * palm[:3, 2] for i in range(1, n + 1)]
        for offset in path:
            world.move_hand(offset)
            world.hold_spread(spread)
            world.hold_fingers_open(fingers)
            world.step()
            if guarded and world.touches():
                offset = world.hand_offset()  # stop where the hand is (it trails its target)
                world.move_hand(offset)
                break
        travel = float(np.dot(offset - backoff, palm[:3, 2]))
        # close; a table pinch's palm rises with the closing fingers' DOF (grasp.pinch)
        rising, up, carriage = grasp.wrist_rise, -palm[:3, 2], offset
        steps, settle_left = 0, round(s.close_settle / s.time_step)
        while steps * s.time_step < s.close_timeout and settle_left > 0:
            if rising is not None:
                carriage = offset + max(rising.at(q) for q in world.finger_dofs_deg()) * up
                world.move_hand(carriage)
            world.hold_spread(spread)
            world.drive_fingers(fingers)
            world.step()
            steps += 1
            if all(f.done for f in fingers):
                settle_left -= 1
        joints_deg = world.joint_values_deg()
        rose = float(np.dot(world.hand_offset() - offset, up))
        contacts = world.n_contacts()
        stops = tuple(f.stop for f in fingers)
        ref_position, ref_rotation = world.object_in_palm()
        # load: gravity on, support gone; the hand lifts from where it closed (a guarded
        # approach stops short of or past the planned pose: going there first would push)
        start = carriage
        world.hold_object(None)
        world.gravity(True)
        slip, held_s, phase, elapsed = 0.0, None, "held", 0.0
        position, rotation = ref_position, ref_rotation
        for name, n_steps, target in _schedule(lift, shake, directions, s):
            for i in range(n_steps):
                world.move_hand(start + target((i + 1) * s.time_step))
                world.hold_spread(spread)
                world.drive_fingers(fingers)
                world.step()
                elapsed += s.time_step
                position, rotation = world.object_in_palm()
                distance = float(np.linalg.norm(position - ref_position))
                slip = max(slip, distance)
                if held_s is None and distance > s.hold_tolerance:
                    held_s, phase = elapsed, name
                if distance > s.drop_distance:
                    break
            else:
                continue
            break
        shifted, tilted = _disturbance(neighbours_at, world.neighbour_poses())

    moved = position - ref_position
    relative = ref_rotation.T @ rotation
    rotation_deg = math.degrees(Rotation.from_matrix(relative).magnitude())
    if held_s is None:
        reason = "held through the lift" + (" and the shakes" if shake else "")
    elif contacts == 0:
        reason = f"the hand closed on nothing; the object fell ({phase})"
    else:
        reason = f"the object left the hand during {phase}, {held_s:.2f} s after gravity came on"
    return LiftResult(
        success=held_s is None,
        reason=reason,
        displacement=float(np.linalg.norm(moved)),
        slip=slip,
        offset=moved,
        rotation_deg=rotation_deg,
        held_s=elapsed if held_s is None else held_s,
        total_s=elapsed,
        phase=phase,
        finger_stops=stops,
        joints_deg=joints_deg,
        mass=world.mass,
        contacts=contacts,
        travel=travel,
        rise=rose,
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
