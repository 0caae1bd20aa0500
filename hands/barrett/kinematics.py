"""BarrettHand kinematics from :class:`BarrettParams`: joints, links, collision shapes, coupling.

This module is the single description of the hand's structure. The URDF
(:mod:`hands.barrett.urdf`) and the collision model used by autograsp (:mod:`grasp.hand.collision`)
are both built from :class:`HandKinematics`, so the two cannot drift apart (a test loads the URDF
in pybullet and compares its link frames with :meth:`HandKinematics.link_poses`).

Frames (all right-handed, metres):

- ``palm``: palm face at z = 0, approach along +z, body from z = 0 down to −``palm_depth``.
- ``fN_knuckle``: x points outward along finger N (the direction the open finger extends),
  z = palm z. Fingers 1 and 2: origin on their spread axis (x = ±25 mm); finger 3: palm centre.
- ``fN_prox``: origin on J2, x along the proximal link, z its inner (grasping) side at J2 = 0.
- ``fN_dist``: origin on J3, x along the distal link toward the tip, z its inner side.

J2 and J3 turn about the link frame's −y axis, so a positive angle swings the finger from "straight
out" toward +z and then over the palm. Joint order everywhere: :data:`JOINT_NAMES`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

# The 8 joints in API order and the 4 DOFs (spread, fingers 1 and 2 together, and one closing DOF
# per finger) are what the wire carries: defined once, with the client (docs/design.md §7).
from grasp_client.wire import DOF_NAMES as DOF_NAMES  # re-exported
from grasp_client.wire import JOINT_NAMES
from hands.barrett.params import BH8_282, BarrettParams

FINGERS: tuple[str, ...] = ("f1", "f2", "f3")
LINK_NAMES: tuple[str, ...] = (
    "palm",
    "f1_knuckle",
    "f1_prox",
    "f1_dist",
    "f2_knuckle",
    "f2_prox",
    "f2_dist",
    "f3_knuckle",
    "f3_prox",
    "f3_dist",
)


def rot_x(angle: float) -> np.ndarray:
    """(3, 3) rotation about x by ``angle`` radians."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle: float) -> np.ndarray:
    """(3, 3) rotation about y by ``angle`` radians."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle: float) -> np.ndarray:
    """(3, 3) rotation about z by ``angle`` radians."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def transform(
    rotation: np.ndarray | None = None, translation: Sequence[float] = (0, 0, 0)
) -> np.ndarray:
    """(4, 4) homogeneous transform from a (3, 3) rotation and a (3,) translation."""
    out = np.eye(4)
    if rotation is not None:
        out[:3, :3] = rotation
    out[:3, 3] = translation
    return out


def axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """(4, 4) rotation by ``angle`` radians about the unit ``axis`` (one of ±x, ±y, ±z)."""
    return rotation_about(axis)(angle)


def axis_rotations(axis: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(S, 4, 4) rotations by each of ``angles`` (radians) about the unit ``axis`` (Rodrigues)."""
    x, y, z = np.asarray(axis, dtype=np.float64)
    cross = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    angles = np.asarray(angles, dtype=np.float64).reshape(-1, 1, 1)
    out = np.tile(np.eye(4), (len(angles), 1, 1))
    out[:, :3, :3] += np.sin(angles) * cross + (1.0 - np.cos(angles)) * (cross @ cross)
    return out


def rotation_about(axis: np.ndarray) -> Callable[[float], np.ndarray]:
    """A fast ``angle -> (4, 4)`` rotation about a coordinate axis (±x, ±y or ±z)."""
    axis = np.asarray(axis, dtype=np.float64)
    index = int(np.argmax(np.abs(axis)))
    if not np.isclose(abs(axis[index]), 1.0) or np.count_nonzero(axis) != 1:
        raise ValueError(f"joint axes must be ±x, ±y or ±z, got {axis}")
    sign = float(np.sign(axis[index]))

    def rotation(angle: float) -> np.ndarray:
        c, s = math.cos(angle), sign * math.sin(angle)
        if index == 0:
            rows = [[1.0, 0.0, 0.0, 0.0], [0.0, c, -s, 0.0], [0.0, s, c, 0.0]]
        elif index == 1:
            rows = [[c, 0.0, s, 0.0], [0.0, 1.0, 0.0, 0.0], [-s, 0.0, c, 0.0]]
        else:
            rows = [[c, -s, 0.0, 0.0], [s, c, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
        return np.array([*rows, [0.0, 0.0, 0.0, 1.0]])

    return rotation


@dataclass(frozen=True)
class JointSpec:
    """One URDF joint: child frame = parent frame · origin · rotation(axis, q)."""

    name: str
    kind: Literal["revolute", "fixed"]
    parent: str
    child: str
    origin: np.ndarray  # (4, 4) child joint frame in the parent link frame at q = 0
    axis: np.ndarray  # (3,) unit axis in the joint frame
    lower_deg: float = 0.0
    upper_deg: float = 0.0


@dataclass(frozen=True)
class Primitive:
    """One collision primitive of a link: a box (full extents) or a cylinder along its local z."""

    link: str
    kind: Literal["box", "cylinder"]
    size: tuple[float, ...]  # box: (sx, sy, sz); cylinder: (radius, length)
    pose: np.ndarray  # (4, 4) primitive frame in the link frame

    def half_extents(self) -> np.ndarray:
        """(3,) half extents of the primitive's bounding box in its own frame."""
        if self.kind == "box":
            return 0.5 * np.asarray(self.size)
        radius, length = self.size
        return np.array([radius, radius, 0.5 * length])

    def corners(self) -> np.ndarray:
        """(8, 3) corners of a box enclosing the primitive, in the link frame."""
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        local = signs * self.half_extents()
        return local @ self.pose[:3, :3].T + self.pose[:3, 3]


class HandKinematics:
    """Joints, collision primitives and forward kinematics of one BarrettHand.

    Parameters
    ----------
    params : BarrettParams
        Dimensions; :data:`BH8_282` by default.
    """

    def __init__(self, params: BarrettParams = BH8_282) -> None:
        self.params = params
        self.joints: tuple[JointSpec, ...] = self._build_joints()
        self.primitives: tuple[Primitive, ...] = self._build_primitives()
        self._joint_by_name = {joint.name: joint for joint in self.joints}
        self._rotation = {
            joint.name: rotation_about(joint.axis) for joint in self.joints if joint.kind != "fixed"
        }

    # -- structure ------------------------------------------------------------------------------
    def _build_joints(self) -> tuple[JointSpec, ...]:
        p = self.params
        up, down = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])
        close = np.array([0.0, -1.0, 0.0])  # J2/J3 axis: swings link x toward +z
        outward_y = rot_z(np.pi / 2)  # knuckle x along palm +y at spread 0
        joints = [
            # Finger 1 turns clockwise seen from +z (toward +x), finger 2 mirror-image.
            JointSpec(
                "f1_spread",
                "revolute",
                "palm",
                "f1_knuckle",
                transform(outward_y, (p.spread_axis_x, 0.0, 0.0)),
                down,
                0.0,
                p.spread_max_deg,
            ),
            JointSpec(
                "f2_spread",
                "revolute",
                "palm",
                "f2_knuckle",
                transform(outward_y, (-p.spread_axis_x, 0.0, 0.0)),
                up,
                0.0,
                p.spread_max_deg,
            ),
            JointSpec(
                "f3_base",
                "fixed",
                "palm",
                "f3_knuckle",
                transform(rot_z(-np.pi / 2)),
                up,
            ),
        ]
        for finger in FINGERS:
            joints.append(
                JointSpec(
                    f"{finger}_prox",
                    "revolute",
                    f"{finger}_knuckle",
                    f"{finger}_prox",
                    transform(None, (p.base_to_proximal, 0.0, p.proximal_axis_z)),
                    close,
                    0.0,
                    p.proximal_max_deg,
                )
            )
            joints.append(
                JointSpec(
                    f"{finger}_dist",
                    "revolute",
                    f"{finger}_prox",
                    f"{finger}_dist",
                    # the fixed distal bend: J3 = 0 already leans the distal link inward
                    transform(rot_y(-np.radians(p.distal_bend_deg)), (p.proximal_length, 0, 0)),
                    close,
                    0.0,
                    p.distal_max_deg,
                )
            )
        return tuple(joints)

    def _build_primitives(self) -> tuple[Primitive, ...]:
        p = self.params
        knuckle_height = p.knuckle_top + p.knuckle_bottom
        prims = [
            Primitive(
                "palm",
                "cylinder",
                (p.palm_radius, p.palm_depth),
                transform(None, (0.0, 0.0, -0.5 * p.palm_depth)),
            )
        ]
        for finger in FINGERS:
            prims.append(
                Primitive(
                    f"{finger}_knuckle",
                    "box",
                    (p.knuckle_width, p.knuckle_width, knuckle_height),
                    transform(
                        None, (p.base_to_proximal, 0.0, 0.5 * (p.knuckle_top - p.knuckle_bottom))
                    ),
                )
            )
            prims.append(
                Primitive(
                    f"{finger}_prox",
                    "box",
                    (p.proximal_length, p.proximal_width, p.proximal_thickness),
                    transform(None, (0.5 * p.proximal_length, 0.0, 0.0)),
                )
            )
            prims.append(
                Primitive(
                    f"{finger}_dist",
                    "box",
                    (p.distal_length, p.distal_width, p.distal_thickness),
                    transform(None, (0.5 * p.distal_length, 0.0, 0.0)),
                )
            )
            # rounded J3 knuckle, filling the wedge between the bent links
            prims.append(
                Primitive(
                    f"{finger}_dist",
                    "cylinder",
                    (0.5 * p.distal_thickness, p.distal_width),
                    transform(rot_x(np.pi / 2)),
                )
            )
        return tuple(prims)

    def joint(self, name: str) -> JointSpec:
        """The :class:`JointSpec` called ``name`` (``f3_base`` is the fixed one)."""
        try:
            return self._joint_by_name[name]
        except KeyError:
            raise ValueError(f"unknown joint {name!r}; expected one of {JOINT_NAMES}") from None

    def primitives_of(self, link: str) -> tuple[Primitive, ...]:
        """The collision primitives of ``link``."""
        if link not in LINK_NAMES:
            raise ValueError(f"unknown link {link!r}; expected one of {LINK_NAMES}")
        return tuple(prim for prim in self.primitives if prim.link == link)

    # -- forward kinematics ---------------------------------------------------------------------
    def knuckle_pose(self, finger: str, spread_rad: float) -> np.ndarray:
        """(4, 4) ``fN_knuckle`` frame in the palm frame at the given spread (radians)."""
        if finger == "f3":
            return self._joint_by_name["f3_base"].origin.copy()
        name = f"{finger}_spread"
        return self._joint_by_name[name].origin @ self._rotation[name](spread_rad)

    def finger_poses(
        self, knuckle: np.ndarray, finger: str, prox_rad: float, dist_rad: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(4, 4) ``fN_prox`` and ``fN_dist`` frames, given the knuckle frame (any parent frame)."""
        j2, j3 = f"{finger}_prox", f"{finger}_dist"
        prox = knuckle @ self._joint_by_name[j2].origin @ self._rotation[j2](prox_rad)
        dist = prox @ self._joint_by_name[j3].origin @ self._rotation[j3](dist_rad)
        return prox, dist

    def finger_path(
        self, knuckles: np.ndarray, finger: str, prox_rad: np.ndarray, dist_rad: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`finger_poses` for many configurations at once: (S, 4, 4) knuckle frames and
        (S,) angles give the (S, 4, 4) ``fN_prox`` and ``fN_dist`` frames."""
        j2, j3 = (self._joint_by_name[f"{finger}_{part}"] for part in ("prox", "dist"))
        prox = knuckles @ j2.origin @ axis_rotations(j2.axis, prox_rad)
        return prox, prox @ j3.origin @ axis_rotations(j3.axis, dist_rad)

    def link_poses(self, joints_rad: Sequence[float]) -> dict[str, np.ndarray]:
        """Every link frame in the palm frame.

        Parameters
        ----------
        joints_rad : (8,) float
            Joint angles in radians, order :data:`JOINT_NAMES`.

        Returns
        -------
        dict mapping each of :data:`LINK_NAMES` to a (4, 4) link→palm transform.
        """
        q = np.asarray(joints_rad, dtype=np.float64)
        if q.shape != (8,):
            raise ValueError(f"joints_rad must have shape (8,), got {q.shape}")
        values = dict(zip(JOINT_NAMES, q, strict=True))
        poses = {"palm": np.eye(4)}
        for finger in FINGERS:
            spread = values.get(f"{finger}_spread", 0.0)
            knuckle = self.knuckle_pose(finger, spread)
            prox, dist = self.finger_poses(
                knuckle, finger, values[f"{finger}_prox"], values[f"{finger}_dist"]
            )
            poses[f"{finger}_knuckle"] = knuckle
            poses[f"{finger}_prox"] = prox
            poses[f"{finger}_dist"] = dist
        return poses


# -- coupling --------------------------------------------------------------------------------------
def finger_joints_deg(
    dof_deg: float, *, proximal_stop_deg: float | None = None, params: BarrettParams = BH8_282
) -> tuple[float, float]:
    """(J2, J3) in degrees for a finger DOF value, with the breakaway clutch.

    While the finger closes freely J2 = DOF and J3 = DOF × ``distal_ratio`` (1/3). Once the
    proximal link has stopped at ``proximal_stop_deg`` (breakaway), J2 stays there and J3 keeps
    following the DOF.
    """
    if not 0.0 <= dof_deg <= params.finger_dof_max_deg + 1e-9:
        raise ValueError(
            f"finger DOF must be in [0, {params.finger_dof_max_deg}] degrees, got {dof_deg}"
        )
    prox = dof_deg if proximal_stop_deg is None else min(dof_deg, proximal_stop_deg)
    return min(prox, params.proximal_max_deg), dof_deg * params.distal_ratio


def joints_from_dofs(
    dofs_deg: Sequence[float],
    *,
    proximal_stops_deg: Sequence[float | None] = (None, None, None),
    params: BarrettParams = BH8_282,
) -> np.ndarray:
    """The 8 joint angles (degrees, :data:`JOINT_NAMES` order) from the 4 DOFs (degrees).

    Parameters
    ----------
    dofs_deg : (4,) float
        spread, finger 1, finger 2, finger 3 (:data:`DOF_NAMES`).
    proximal_stops_deg : (3,) float or None
        J2 angle at which each finger's proximal link stopped (breakaway), or None.
    """
    dofs = np.asarray(dofs_deg, dtype=np.float64)
    if dofs.shape != (4,):
        raise ValueError(f"dofs_deg must have shape (4,), got {dofs.shape}")
    if not 0.0 <= dofs[0] <= params.spread_max_deg:
        raise ValueError(f"spread must be in [0, {params.spread_max_deg}] degrees, got {dofs[0]}")
    fingers = [
        finger_joints_deg(dof, proximal_stop_deg=stop, params=params)
        for dof, stop in zip(dofs[1:], proximal_stops_deg, strict=True)
    ]
    spread = dofs[0]
    return np.array([spread, *fingers[0], spread, *fingers[1], *fingers[2]])
