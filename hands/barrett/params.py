"""BarrettHand BH8-282 dimensions, joint ranges and coupling: one frozen dataclass.

Every number comes from ``hands/barrett/README.md`` (a digest of GraspIt!'s ``Barrett.xml``, the
ROS ``bh282.urdf.xacro`` and Barrett's DH table). Where the sources disagree, its "used" column
is followed and the alternatives are named in the comment next to the field. Numbers that
none of the sources give (marked "chosen") are filled in so that the primitives are consistent
with the quoted dimensions; they only affect the collision shapes and the URDF inertias.

Lengths are metres, angles degrees (as the docs quote them); code converts to radians.

Palm frame (docs/design.md §7): palm face at z = 0, approach along +z, the palm body below the face.
Finger 1 spreads about the axis at x = +25 mm, finger 2 about x = −25 mm (mirror image), finger 3
sits at y = −50 mm with no spread. At spread 0 fingers 1 and 2 point along +y, opposite finger 3.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class BarrettParams:
    """Kinematic and collision parameters of one BarrettHand (metres, degrees)."""

    # --- palm --------------------------------------------------------------------------------
    #: palm cylinder radius, Ø89 mm (ROS URDF collision cylinder: r = 45 mm).
    palm_radius: float = 0.0445
    #: palm body from the face z = 0 down to about −80 mm.
    palm_depth: float = 0.080

    # --- knuckles and finger bases -----------------------------------------------------------
    #: spread axes of fingers 1 and 2, parallel to palm z, at x = ±25 mm.
    spread_axis_x: float = 0.025
    #: spread axis → proximal (J2) axis, DH a1 = 50 mm. Finger 3's J2 axis is 50 mm from the palm
    #: centre at y = −50 mm (one public URDF mirrors it to +50 mm; not followed).
    base_to_proximal: float = 0.050
    #: height of the J2 axes above the palm face ("~0" in all sources).
    proximal_axis_z: float = 0.0
    #: knuckle housing size along the J2 axis and along the finger: 25 mm.
    knuckle_width: float = 0.025
    #: knuckle housing rises about 12 mm above the palm face (quoted for finger 3; used for all).
    knuckle_top: float = 0.012
    #: how far the housing reaches below the palm face (chosen: not in the sources).
    knuckle_bottom: float = 0.020

    # --- links -------------------------------------------------------------------------------
    #: proximal link J2 → J3: 70 mm (URDF: 69.9 mm plus a 3 mm lateral offset, not modelled).
    proximal_length: float = 0.070
    #: proximal link width along its joint axis: 19–21 mm, middle value.
    proximal_width: float = 0.020
    #: proximal link thickness, ~26 mm including the housing, centred on the link's axis line.
    proximal_thickness: float = 0.026
    #: distal link J3 → fingertip: 55 mm, tip about 57 (DH table: 50 plus d3 = 9.5).
    distal_length: float = 0.055
    #: distal link width along its joint axis: 23 mm.
    distal_width: float = 0.023
    #: distal link thickness ~20 mm, centred on the link's axis line.
    distal_thickness: float = 0.020
    #: fixed bend of the distal link toward closing at J3 = 0: +40° (GraspIt, which also adds +5°
    #: on J2, not modelled here; DH table 42°; URDF 45°).
    distal_bend_deg: float = 40.0

    # --- joint ranges and coupling -----------------------------------------------------------
    #: spread of fingers 1 and 2 (one DOF, mirror image): 0–180°.
    spread_max_deg: float = 180.0
    #: proximal J2: 0–140° (GraspIt: 144°). 0 = finger straight out, flat with the palm.
    proximal_max_deg: float = 140.0
    #: distal J3: 0–48°.
    distal_max_deg: float = 48.0
    #: J3 = ratio × DOF while a finger closes (and after breakaway): 1/3.
    distal_ratio: float = 1.0 / 3.0
    #: largest value of a finger DOF (the motor angle, in units of J2): the J2 limit, so J3 stays at
    #: most 140/3 = 46.7°, inside its 48° limit.
    finger_dof_max_deg: float = 140.0

    # --- masses for the URDF (chosen: the hand weighs about 1.2 kg; kinematic use ignores them) --
    palm_mass: float = 0.60
    knuckle_mass: float = 0.05
    proximal_mass: float = 0.10
    distal_mass: float = 0.05

    def __post_init__(self) -> None:
        lengths = {
            name: getattr(self, name)
            for name in (
                "palm_radius",
                "palm_depth",
                "base_to_proximal",
                "knuckle_width",
                "proximal_length",
                "proximal_width",
                "proximal_thickness",
                "distal_length",
                "distal_width",
                "distal_thickness",
            )
        }
        bad = [name for name, value in lengths.items() if not value > 0.0]
        if bad:
            raise ValueError(f"BarrettParams: lengths must be positive, got {bad}")
        if not 0.0 < self.distal_ratio <= 1.0:
            raise ValueError(f"distal_ratio must be in (0, 1], got {self.distal_ratio}")
        if self.finger_dof_max_deg * self.distal_ratio > self.distal_max_deg + 1e-9:
            raise ValueError("finger_dof_max_deg × distal_ratio exceeds the distal joint limit")


#: The BH8-282 as hands/barrett/README.md describes it.
BH8_282 = BarrettParams()
