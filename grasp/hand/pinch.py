"""The table pinch: fingertips that slide in along the table while the wrist rises.

A flat object (a plate, a coin, a hammer lying down) is lower than where a closing finger of
the BarrettHand sweeps over the table, so an ordinary grasp from above closes over it. A person,
or a hand on an arm, pinches it instead: the fingertips are put down beside it on the table and
the fingers close while the wrist rises just enough to keep the tips on the table, so that they
slide in under and around the object (Eppner et al., "Exploitation of environmental constraints
in human and robotic grasping", 2015; Erdogan, Schröder and Brock, "Coordination of intrinsic
and extrinsic degrees of freedom in soft robotic grasping").

The motion, as the planner plans it and the lift test executes it:

1. The open hand faces the table (palm +z along −n, the plane's normal) and goes down until
   its lowest point is :data:`TIP_CLEARANCE_M` above the table (at DOF 0 that is the distal
   links' outer edges: the BH8-282's distal links are bent 40° toward the palm).
2. The fingers close, all three at the same commanded DOF, and the palm moves along n so that
   the hand's deepest point stays where it started: its rise is the largest of :func:`rise`
   (DOF) over the three fingers, :func:`rise` being how much deeper below the palm face a
   finger at that DOF reaches than an open one. The palm goes up by 70 mm while the fingers
   close to 65° (the tips sweep in from 16 cm to 5 cm from the palm's axis) and back down by 15
   mm by 90° (the tips meet under the palm): the tips stay :data:`TIP_CLEARANCE_M` above the
   table, and no link, a stopped finger's included, goes below them.
3. A finger that touches the object stops (Barrett rules, breakaway included); its DOF, and so
   its share of the rise, stays where it stopped; when all have stopped the palm stops too. A
   stopped finger keeps its motor's torque: when the palm's motion takes its link off the
   object, it closes on until it touches again.

The rise is a function of the fingers' DOFs alone, from the hand's geometry: a robot runs it as
a synchronised trajectory (wrist height against the DOFs it reads from the hand), which needs no
force sensing; :func:`profile` is the table it interpolates (docs/service.md, "Executing a table
pinch"). The alternative, pressing the wrist down with a force limit and letting the table push
it up, needs a force-controlled arm and depends on the table's friction; it is not modelled.

This module must not import torch (docs/design.md §2).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np

from grasp.hand.closing import ANGLE_TOL_RAD, Search, close_finger, shift, speed_bounds
from grasp_client.wire import SupportPlane, WristRise
from hands.barrett import BH8_282, FINGERS, BarrettParams, HandKinematics

__all__ = ["PROFILE_STEP_DEG", "TABLE_PINCH", "TIP_CLEARANCE_M", "close_pinching", "depth",
           "faces_table", "pinch_failure", "pinch_height", "profile", "rise"]

#: The grasp kind (``GraspResult.kind``, the wire's ``kind``).
TABLE_PINCH = "table pinch"
#: The open hand's lowest point starts this far above the table, and the closing fingertips
#: sweep this far above it (metres): under the 1 cm a plate stands, over a table's unevenness.
TIP_CLEARANCE_M = 0.002
#: Spacing of the rise profile's samples in finger DOF (degrees); the rise between two is linear.
PROFILE_STEP_DEG = 2.5
#: The palm must face the table this exactly (cosine of the angle between +z and −n).
FACING_TOL = 1e-6


def faces_table(palm_pose: np.ndarray, plane: SupportPlane) -> bool:
    """Whether the palm's +z points straight down ``plane``'s normal (the pinch's posture)."""
    return float(np.asarray(palm_pose)[:3, 2] @ plane.normal) <= -1.0 + FACING_TOL


def pinch_height(params: BarrettParams = BH8_282) -> float:
    """Height (m) of the palm face above the table where a table pinch starts closing: objects
    lower than this get table pinch candidates
    (:func:`grasp.search.candidates.table_candidates`)."""
    return depth(0.0, params) + TIP_CLEARANCE_M


def depth(dof_rad: float, params: BarrettParams = BH8_282) -> float:
    """Depth (m) below the palm face of the hand's deepest point with every finger at
    ``dof_rad`` (J2 = DOF up to its limit, J3 = DOF / 3), at any spread."""
    kinematics = _kinematics(params)
    j2, j3 = min(dof_rad, math.radians(params.proximal_max_deg)), params.distal_ratio * dof_rad
    links = kinematics.link_poses(np.array([0.0, j2, j3, 0.0, j2, j3, j2, j3]))
    below = SupportPlane(np.array([0.0, 0.0, -1.0]), 0.0)  # height = −depth in the palm frame
    return max(-float(below.lowest(p.kind, p.size, links[p.link] @ p.pose))
               for p in kinematics.primitives)


@functools.lru_cache(maxsize=8)
def profile(params: BarrettParams = BH8_282) -> tuple[np.ndarray, np.ndarray]:
    """The rise table: (k,) finger DOFs (degrees, every :data:`PROFILE_STEP_DEG` from 0 to the
    DOF's maximum) and (k,) palm rises (m) along the table's normal, :func:`depth` less the open
    hand's; rise(0) = 0. Between samples the rise is linear (:func:`rise`): within 0.1 mm of the
    exact curve (tests), well inside :data:`TIP_CLEARANCE_M`."""
    top = params.finger_dof_max_deg
    dofs = np.append(np.arange(0.0, top, PROFILE_STEP_DEG), top)
    deepest = np.array([depth(math.radians(q), params) for q in dofs])
    return dofs, deepest - deepest[0]


def rise(dof_deg: float | np.ndarray, params: BarrettParams = BH8_282) -> float | np.ndarray:
    """The palm rise (m) along the table's normal that a finger at ``dof_deg`` needs; the palm
    takes the largest of its fingers'."""
    return np.interp(dof_deg, *profile(params))


def pinch_failure(results: Sequence) -> str | None:
    """Why none of the table pinches among ``results`` (autograsped, not necessarily scored) is
    a grasp, in words: the one whose fingers touched the object most, what its fingers did; None
    without table pinches."""
    pinches = [r for r in results if r.kind == TABLE_PINCH]
    tried = [r for r in results if r.kind != TABLE_PINCH and r.reason.startswith("table pinch:")]
    if not pinches:
        return (None if not tried else f"table pinches: {len(tried)} tried, each met the object "
                "on its way down (it is too tall under the palm for the tips to reach the table)")

    def touching(r) -> set[str]:
        return {c.link[:2] for c in r.contacts if c.link[:2] in FINGERS}

    best = max(pinches, key=lambda r: (len(touching(r)), len(r.contacts)))
    missed = [f for f, stop in zip(FINGERS, best.finger_stops, strict=True)
              if stop.endswith("limit") and f not in touching(best)]
    said = f"table pinches: {len(pinches) + len(tried)} tried, at best "
    said += f"{len(touching(best))} finger(s) touched it"
    if missed:
        said += f", {', '.join(missed)} closed under the palm untouched (it lies between them)"
    return said


def close_pinching(
    search: Search, palm: np.ndarray, spread: float, step: float
) -> tuple[np.ndarray, list[tuple[float, float, float, str]], WristRise]:
    """Close a table pinch from ``palm`` (steps 2 and 3 above): the lock-step phase with the palm
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
        lifted, out = shift(palm, -max(float(rise(math.degrees(dof), params)), floor)), {}
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
    speed = max(speed_bounds(search.scene, f)[0] for f in FINGERS) + slope
    # the lock-step phase: every finger still closing at the same DOF, the palm rising with it,
    # until each touched something (a proximal touch breaks away: J2 stops, the DOF goes on) or
    # reached its limit; a stopped finger keeps its share of the rise (floor)
    moving: dict[str, tuple[str, float]] = {f: ("coupled", 0.0) for f in FINGERS}
    stopped: dict[str, tuple[str, float, float]] = {}
    dof, floor = 0.0, 0.0
    while moving:
        dof, hit = search.first_contact(lambda t, floor=floor: poses_at(t, moving, floor), dof,
                                        dof_max, step=step, speed=speed, tol=ANGLE_TOL_RAD)
        for f, (mode, j2) in list(moving.items()):
            j2 = min(dof, j2_max) if mode == "coupled" else j2
            prefix = "breakaway-" if mode == "breakaway" else ""
            if not hit or f"{f}_dist" in hit:
                stopped[f] = (prefix + ("distal" if hit else "limit"), dof, j2)
                del moving[f]
                floor = max(floor, float(rise(math.degrees(dof), params)))
            elif f"{f}_prox" in hit:
                moving[f] = ("breakaway", j2)
    end = max(float(rise(math.degrees(q), params)) for _, q, _ in stopped.values())
    lifted = shift(palm, -end)
    fingers = []
    for f in FINGERS:
        stop, q, j2 = stopped[f]
        if stop.endswith("distal"):  # still driven: it closes on to the object, if the palm's
            # motion took it off (the palm now still)
            frozen = j2 if stop.startswith("breakaway") else None
            fingers.append(close_finger(search, lifted @ knuckles[f], f, step, q, frozen))
        else:
            fingers.append((q, j2, ratio * q, stop))
    wrist = WristRise(dofs.tolist(), rises.tolist(), end)
    return lifted, fingers, wrist


@functools.lru_cache(maxsize=8)
def _kinematics(params: BarrettParams) -> HandKinematics:
    return HandKinematics(params)
