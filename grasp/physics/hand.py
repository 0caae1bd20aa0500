"""The BarrettHand in a pybullet client: one loader for both worlds, the lift test's dynamic one
(:mod:`grasp.physics.world`) and the evaluation's picture world (:mod:`grasp.evaluate.picture`)."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import NamedTuple

from completion.bullet import pybullet
from hands.barrett import BarrettParams
from hands.barrett.urdf import urdf_string


class JointInfo(NamedTuple):
    """The fields of ``getJointInfo`` that matter here (angles in radians)."""

    index: int
    name: str
    kind: int  # pybullet.JOINT_REVOLUTE or pybullet.JOINT_FIXED
    lower: float
    upper: float
    child_link: str


def load_hand(client, params: BarrettParams, *,
              fixed_base: bool) -> tuple[int, dict[str, JointInfo]]:
    """The hand from its generated URDF (:mod:`hands.barrett.urdf`) in ``client``, with implicit
    cylinders (pybullet would otherwise pad the palm's hull by its margin) and the URDF's
    inertia; its body id and its joints by name."""
    with tempfile.TemporaryDirectory() as tmp:
        urdf = Path(tmp) / "barrett.urdf"
        urdf.write_text(urdf_string(params))
        hand = client.loadURDF(
            str(urdf),
            useFixedBase=fixed_base,
            flags=pybullet.URDF_USE_INERTIA_FROM_FILE | pybullet.URDF_USE_IMPLICIT_CYLINDER,
        )
    joints: dict[str, JointInfo] = {}
    for index in range(client.getNumJoints(hand)):
        info = client.getJointInfo(hand, index)
        joints[info[1].decode()] = JointInfo(
            index, info[1].decode(), info[2], info[8], info[9], info[12].decode()
        )
    return hand, joints
