"""Canonical grasp scenes for the BarrettHand regression tests (shared by the grasp test files).

Every scene puts the palm at the world origin looking up (+z) unless it says otherwise, so the
numbers read directly in the palm frame of docs/design.md §7: fingers 1 and 2 on the +y side (spread
0), finger 3 on the −y side. Objects stand on or above the plane z = 0.05 m in front of the palm,
which starts 5 cm below them and approaches.

The golden joint values live in ``tests/golden/grasps.json``. They are never rewritten by a test
run. To regenerate them on purpose (after a deliberate change to the hand or to autograsp; say
why in the change's note), run::

    GRASP_REGENERATE_GOLDEN=1 python -m pytest tests/test_autograsp.py -k golden
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

GOLDEN_PATH = Path(__file__).parent / "golden" / "grasps.json"
REGENERATE_ENV = "GRASP_REGENERATE_GOLDEN"
#: Palm start: 5 cm below the plane z = 0 the objects stand on.
START = np.array(
    [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, -0.05], [0.0, 0.0, 0.0, 1.0]]
)


@dataclass(frozen=True)
class Scene:
    """A mesh, an initial palm pose, a spread and whether to approach."""

    name: str
    mesh: trimesh.Trimesh
    palm_pose: np.ndarray = field(default_factory=START.copy)
    spread_deg: float = 0.0
    approach: bool = True


def box(extents, center) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_translation(center)
    return mesh


def lying_cylinder(radius: float, length: float = 0.2) -> trimesh.Trimesh:
    """Cylinder along x resting on z = 0 (axis at height ``radius``)."""
    mesh = trimesh.creation.cylinder(radius=radius, height=length, sections=96)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    mesh.apply_translation([0.0, 0.0, radius])
    return mesh


def mug() -> trimesh.Trimesh:
    """Upright mug (open side up) with its handle toward finger 3 (−y): a composite soup."""
    wall = trimesh.creation.annulus(r_min=0.035, r_max=0.040, height=0.10, sections=64)
    wall.apply_translation([0.0, 0.0, 0.05])
    bottom = trimesh.creation.cylinder(radius=0.040, height=0.008, sections=64)
    bottom.apply_translation([0.0, 0.0, 0.004])
    handle = trimesh.creation.torus(major_radius=0.025, minor_radius=0.006)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    handle.apply_translation([0.0, -0.055, 0.05])
    return trimesh.util.concatenate([wall, bottom, handle])


def breakaway_bar() -> Scene:
    """A bar over finger 3's proximal link: the proximal stops on it, the distal closes on."""
    bar = box((0.06, 0.04, 0.03), (0.0, -0.08, 0.045))  # y in [-0.10, -0.06], z in [0.03, 0.06]
    return Scene("breakaway_bar", bar, palm_pose=np.eye(4), approach=False)


def scenes() -> list[Scene]:
    """The canonical scenes, in golden-file order."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    sphere.apply_translation([0.0, 0.0, 0.05])
    far_sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
    far_sphere.apply_translation([0.30, 0.0, 0.05])
    upright = trimesh.creation.cylinder(radius=0.03, height=0.15, sections=96)
    upright.apply_translation([0.0, 0.0, 0.075])
    return [
        Scene("box_small", box((0.04, 0.04, 0.06), (0.0, 0.0, 0.03))),
        Scene("box_long", box((0.20, 0.06, 0.10), (0.0, 0.0, 0.05))),
        Scene("box_large", box((0.12, 0.12, 0.10), (0.0, 0.0, 0.05))),
        Scene("cylinder_upright", upright),
        Scene("cylinder_lying", lying_cylinder(0.035)),
        Scene("sphere_tripod", sphere, spread_deg=60.0),
        Scene("mug", mug()),
        Scene("plate_thin", box((0.10, 0.004, 0.12), (0.0, 0.0, 0.06))),
        Scene("miss", far_sphere),
        breakaway_bar(),
    ]


@functools.cache
def scene_result(name: str):
    """(mesh, GraspResult) of one canonical scene, computed once per test session."""
    from grasp.hand.autograsp import autograsp

    scene = {s.name: s for s in scenes()}[name]
    result = autograsp(
        scene.mesh, scene.palm_pose, spread_deg=scene.spread_deg, approach=scene.approach
    )
    return scene.mesh, result


def summary(result) -> dict:
    """What a golden records about a :class:`grasp.hand.autograsp.GraspResult`."""
    return {
        "joints_deg": [round(float(v), 4) for v in result.joints_deg],
        "dofs_deg": [round(float(v), 4) for v in result.dofs_deg],
        "travel_mm": round(1000.0 * result.travel, 4),
        "finger_stops": list(result.finger_stops),
        "success": bool(result.success),
    }


def load_golden() -> dict:
    return json.loads(GOLDEN_PATH.read_text()) if GOLDEN_PATH.exists() else {}


def write_golden(data: dict) -> None:
    GOLDEN_PATH.parent.mkdir(parents=True, exist_ok=True)
    GOLDEN_PATH.write_text(json.dumps(data, indent=1) + "\n")
