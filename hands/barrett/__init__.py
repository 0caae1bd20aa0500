"""The BarrettHand BH8-282: parameters, kinematics and coupling, URDF.

``BarrettParams`` holds every number (from ``hands/barrett/README.md``), ``HandKinematics`` turns
them
into joints, links and collision primitives, and :mod:`hands.barrett.urdf` writes the URDF that
pybullet loads.
"""

from hands.barrett.kinematics import (
    DOF_NAMES,
    FINGERS,
    JOINT_NAMES,
    LINK_NAMES,
    HandKinematics,
    finger_joints_deg,
    joints_from_dofs,
)
from hands.barrett.params import BH8_282, BarrettParams

__all__ = [
    "BH8_282",
    "DOF_NAMES",
    "FINGERS",
    "JOINT_NAMES",
    "LINK_NAMES",
    "BarrettParams",
    "HandKinematics",
    "finger_joints_deg",
    "joints_from_dofs",
]
