"""The table an object rests on, and the hand against it.

:class:`SupportPlane` (defined with the wire types in :mod:`grasp_client.wire`, where it is parsed
and checked) is the surface (n·x + d = 0, n up, the object on its upper side): given on ``POST
/views`` or ``GET /grasp``, it cuts the completion (:mod:`completion.stream`) and is an obstacle to
the hand as in GraspIt! (an fcl halfspace in :class:`grasp.hand.collision.CollisionScene`; the
approach and every finger stop at it, :mod:`grasp.hand.autograsp`). The functions below place the
hand's collision primitives by its kinematics and measure how far the hand of a grasp stays above
the plane: the planner drops any grasp that crosses it (:func:`crosses`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np

from completion.grid import transform_points
from grasp_client.wire import SupportPlane
from hands.barrett import HandKinematics

__all__ = ["TABLE_TOL_M", "crosses", "hand_clearance", "hand_points", "hand_primitives",
           "to_upright"]

#: A grasp whose hand reaches further below the table is dropped (only rounding can put it there).
TABLE_TOL_M = 1e-6

_KINEMATICS = HandKinematics()


class HandPose(Protocol):
    """What the functions below read of a grasp (a :class:`grasp.hand.autograsp.GraspResult`)."""

    end_palm_pose: np.ndarray  # (4, 4) palm→world where the fingers closed
    joints_deg: Sequence[float]  # in hands.barrett.JOINT_NAMES order


def _link_poses(grasp: HandPose) -> dict[str, np.ndarray]:
    """Every link's (4, 4) link→world pose in ``grasp``, by the hand's kinematics."""
    joints = np.radians(np.asarray(grasp.joints_deg, dtype=np.float64))
    palm = np.asarray(grasp.end_palm_pose)
    return {link: palm @ pose for link, pose in _KINEMATICS.link_poses(joints).items()}


def hand_primitives(grasp: HandPose) -> list[tuple[str, str, tuple[float, ...], np.ndarray]]:
    """The hand of ``grasp`` as collision primitives placed by the hand's kinematics:
    (link, "box" or "cylinder", size, (4, 4) primitive→world pose) each. Box sizes are full
    extents; a cylinder is (radius, length) along its local z."""
    links = _link_poses(grasp)
    return [
        (prim.link, prim.kind, tuple(prim.size), links[prim.link] @ prim.pose)
        for prim in _KINEMATICS.primitives
    ]


def hand_points(grasp: HandPose) -> np.ndarray:
    """(n, 3) points on the hand's collision primitives in ``grasp`` (world): every box's
    corners and 64 points around each rim of every cylinder."""
    angles = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
    out = []
    for _, kind, size, pose in hand_primitives(grasp):
        if kind == "box":
            local = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
            local = 0.5 * local * np.asarray(size)
        else:
            rim = np.c_[size[0] * np.cos(angles), size[0] * np.sin(angles), np.zeros(64)]
            local = np.concatenate([rim + [0.0, 0.0, z] for z in (-size[1] / 2, size[1] / 2)])
        out.append(transform_points(local, pose))
    return np.concatenate(out)


def hand_clearance(plane: SupportPlane, grasp: HandPose) -> float:
    """Height (m) of the hand's lowest point above ``plane`` in ``grasp`` (negative: below)."""
    return float(
        min(plane.lowest(kind, size, pose) for _, kind, size, pose in hand_primitives(grasp))
    )


def to_upright(plane: SupportPlane) -> np.ndarray:
    """(4, 4) rigid transform from ``plane``'s frame to one where the plane is z = 0 with its
    normal along +z (the frame a z-up simulation needs): a rotation taking n to +z
    (:func:`trimesh.geometry.align_vectors`), then the plane's offset. Exactly the identity for
    the plane z = 0 itself."""
    from trimesh.geometry import align_vectors

    out = np.array(align_vectors(plane.normal, [0.0, 0.0, 1.0]), dtype=np.float64)
    out[2, 3] = plane.offset  # z' = n·x + d
    return out


def crosses(plane: SupportPlane, grasp: HandPose, *, tol: float = TABLE_TOL_M) -> bool:
    """Whether any part of the hand reaches more than ``tol`` below the support plane."""
    return hand_clearance(plane, grasp) < -tol
