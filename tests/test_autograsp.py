"""grasp.hand.autograsp: scripted grasp regression tests on canonical scenes.

Goldens: ``tests/golden/grasps.json``, compared at 0.1°. A failing golden is a behaviour change:
find out why. Regenerate only on purpose (and say why in the change's note) with::

    GRASP_REGENERATE_GOLDEN=1 python -m pytest tests/test_autograsp.py -k golden

Analytic checks use an independent 2-D model of one finger in its closing plane, built only from
the hand's dimensions (:data:`hands.barrett.BH8_282`), against box cross-sections.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import trimesh
from grasp_scenes import (
    GOLDEN_PATH,
    REGENERATE_ENV,
    START,
    box,
    breakaway_bar,
    load_golden,
    lying_cylinder,
    scenes,
    summary,
    write_golden,
)
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from grasp.hand.autograsp import autograsp, pregrasp_pose, regrasp, with_quality
from grasp.hand.collision import CollisionScene
from grasp.hand.result import GraspResult, joint_error_deg
from hands.barrett import BH8_282, JOINT_NAMES

SCENES = {scene.name: scene for scene in scenes()}
ANGLE_TOL_DEG = 0.1
TRAVEL_TOL_MM = 0.1


def grasp(scene, **options) -> GraspResult:
    return autograsp(
        scene.mesh,
        scene.palm_pose,
        spread_deg=scene.spread_deg,
        approach=scene.approach,
        **options,
    )


@pytest.fixture(scope="module")
def results() -> dict[str, GraspResult]:
    return {name: grasp(scene) for name, scene in SCENES.items()}


# -- goldens -------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(SCENES))
def test_golden(name, results):
    """Joint values of the canonical scenes equal tests/golden/grasps.json to 0.1°.

    To regenerate on purpose: GRASP_REGENERATE_GOLDEN=1 python -m pytest tests/test_autograsp.py
    -k golden (then review the diff and say why it changed).
    """
    got = summary(results[name])
    if os.environ.get(REGENERATE_ENV):
        golden = load_golden()
        golden[name] = got
        write_golden(golden)
        pytest.skip(f"regenerated {GOLDEN_PATH.name}[{name}]")
    golden = load_golden()
    assert name in golden, (
        f"no golden for {name!r} in {GOLDEN_PATH}; create it on purpose with "
        f"{REGENERATE_ENV}=1 python -m pytest tests/test_autograsp.py -k golden"
    )
    want = golden[name]
    hint = (
        f"{name}: grasp changed; if on purpose, regenerate with {REGENERATE_ENV}=1 (see module doc)"
    )
    np.testing.assert_allclose(
        got["joints_deg"], want["joints_deg"], atol=ANGLE_TOL_DEG, err_msg=hint
    )
    np.testing.assert_allclose(got["dofs_deg"], want["dofs_deg"], atol=ANGLE_TOL_DEG, err_msg=hint)
    assert got["travel_mm"] == pytest.approx(want["travel_mm"], abs=TRAVEL_TOL_MM), hint
    assert got["finger_stops"] == want["finger_stops"], hint
    assert got["success"] == want["success"], hint


def test_golden_file_covers_every_scene():
    assert set(json.loads(GOLDEN_PATH.read_text())) == set(SCENES)
    assert len(SCENES) >= 8


# -- an independent 2-D model of one finger --------------------------------------------------------
def _rect(origin, angle, length, thickness):
    """(4, 2) corners of a link rectangle from ``origin`` along ``angle`` in the (r, z) plane."""
    d = np.array([math.cos(angle), math.sin(angle)])
    n = np.array([-d[1], d[0]])
    return np.array(
        [origin + s * d + c * n for s in (0, length) for c in (-thickness / 2, thickness / 2)]
    )


def finger_shapes(j2_deg: float, j3_deg: float, p=BH8_282):
    """Proximal and distal rectangles and the J3 disc in the finger's (r, z) plane.

    r runs outward along the finger from its base, z along the approach axis; J2 sits at
    (base_to_proximal, proximal_axis_z).
    """
    t2 = math.radians(j2_deg)
    phi = t2 + math.radians(p.distal_bend_deg + j3_deg)
    j2 = np.array([p.base_to_proximal, p.proximal_axis_z])
    j3 = j2 + p.proximal_length * np.array([math.cos(t2), math.sin(t2)])
    prox = _rect(j2, t2, p.proximal_length, p.proximal_thickness)
    dist = _rect(j3, phi, p.distal_length, p.distal_thickness)
    return {"prox": prox, "dist": dist, "disc": (j3, p.distal_thickness / 2)}


def _axes(poly):
    hull = poly[[0, 1, 3, 2]]  # rectangle corners in order around
    edges = np.roll(hull, -1, axis=0) - hull
    normals = np.stack([-edges[:, 1], edges[:, 0]], axis=1)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def separation(a, b) -> float:
    """Separating-axis gap of two rectangles: > 0 apart, 0 touching, < 0 overlapping."""
    gaps = []
    for n in np.vstack([_axes(a), _axes(b)]):
        pa, pb = a @ n, b @ n
        gaps.append(max(pb.min() - pa.max(), pa.min() - pb.max()))
    return max(gaps)


def _cross2(a, b) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def disc_separation(disc, rect) -> float:
    """Gap between a disc (centre, radius) and a rectangle: > 0 apart, < 0 overlapping."""
    center, radius = disc
    ring = rect[[0, 1, 3, 2]]
    edges = list(zip(ring, np.roll(ring, -1, axis=0), strict=True))
    turns = [_cross2(b - a, center - a) for a, b in edges]
    inside = all(s >= 0 for s in turns) or all(s <= 0 for s in turns)
    dist = min(
        np.linalg.norm(
            center - (a + np.clip(np.dot(center - a, b - a) / np.dot(b - a, b - a), 0, 1) * (b - a))
        )
        for a, b in edges
    )
    return (-dist if inside else dist) - radius


def link_gap(shapes, links, obstacle) -> tuple[float, str]:
    gaps = []
    if "prox" in links:
        gaps.append((separation(shapes["prox"], obstacle), "prox"))
    if "dist" in links:
        gaps.append((separation(shapes["dist"], obstacle), "dist"))
        gaps.append((disc_separation(shapes["disc"], obstacle), "dist"))
    return min(gaps)


def first_contact(gap, lo, hi, step=0.05) -> float | None:
    """Smallest x in [lo, hi] with gap(x) = 0 (scan, then Brent), None if gap stays positive."""
    x = lo
    while x < hi:
        nxt = min(x + step, hi)
        if gap(nxt) <= 0.0:
            return brentq(gap, x, nxt, xtol=1e-9)
        x = nxt
    return None


def reference_close(obstacle, p=BH8_282) -> tuple[float, float, str]:
    """(J2, J3, stop) of one finger closing against a rectangle, with breakaway (2-D model)."""
    ratio, top = p.distal_ratio, p.finger_dof_max_deg

    def both(q):
        return link_gap(finger_shapes(q, ratio * q), ("prox", "dist"), obstacle)[0]

    q = first_contact(both, 0.0, top)
    if q is None:
        return top, ratio * top, "limit"
    if (
        link_gap(finger_shapes(q + 1e-6, ratio * (q + 1e-6)), ("prox", "dist"), obstacle)[1]
        == "dist"
    ):
        return q, ratio * q, "distal"
    q2 = first_contact(
        lambda d: link_gap(finger_shapes(q, ratio * d), ("dist",), obstacle)[0], q, top
    )
    if q2 is None:
        return q, ratio * top, "breakaway-limit"
    return q, ratio * q2, "breakaway-distal"


def rectangle(r0, r1, z0, z1):
    return np.array([[r0, z0], [r0, z1], [r1, z0], [r1, z1]], dtype=np.float64)


# -- analytic checks -------------------------------------------------------------------------------
def test_box_approached_flat_palm_on_face_and_distal_tips_on_sides(results):
    """Box 60 mm wide (|y| ≤ 30 mm) fits inside the knuckles: the palm face lands on its bottom
    face (50 mm travel), and each finger stops when its distal link reaches the side face."""
    res = results["box_long"]
    assert res.travel == pytest.approx(0.05, abs=1e-4)
    bottom = 0.05 - res.travel  # box bottom in the final palm frame
    # in every finger's plane the box is r in [-30, 30] mm (fingers 1, 2 at x = ±25 lie inside
    # its 200 mm length)
    j2, j3, stop = reference_close(rectangle(-0.03, 0.03, bottom, bottom + 0.1))
    assert stop == "distal"
    assert 60.0 < j2 < 80.0
    for finger in ("f1", "f2", "f3"):
        assert res.joint(f"{finger}_prox") == pytest.approx(j2, abs=ANGLE_TOL_DEG)
        assert res.joint(f"{finger}_dist") == pytest.approx(j3, abs=ANGLE_TOL_DEG)
    assert res.finger_stops == ("distal",) * 3
    assert res.success and {c.link for c in res.contacts} >= {
        "palm",
        "f1_dist",
        "f2_dist",
        "f3_dist",
    }


def test_box_wider_than_knuckles_stops_on_proximal_links(results):
    """Box 120 mm wide: the open proximal links (13 mm above the palm face: half their 26 mm
    thickness) touch its bottom first; they cannot close (J2 = 0, breakaway) and the distal links
    swing to their limit without reaching the sides."""
    res = results["box_large"]
    assert res.travel == pytest.approx(0.05 - BH8_282.proximal_thickness / 2, abs=1e-4)
    bottom = 0.05 - res.travel
    j2, j3, stop = reference_close(rectangle(-0.06, 0.06, bottom, bottom + 0.1))
    # J2 = 0 up to the approach's 0.01 mm gap
    assert (j2, stop) == (pytest.approx(0.0, abs=ANGLE_TOL_DEG), "breakaway-limit")
    for finger in ("f1", "f2", "f3"):
        assert res.joint(f"{finger}_prox") == pytest.approx(0.0, abs=ANGLE_TOL_DEG)
        assert res.joint(f"{finger}_dist") == pytest.approx(j3, abs=1e-9)
    assert res.finger_stops == ("breakaway-limit",) * 3
    assert not res.success


def test_breakaway_proximal_blocked_distal_keeps_closing(results):
    """A bar over finger 3: the proximal link's top face meets the bar's outer bottom edge at
    (r, z) = (100, 30) mm where −(100 − 50)·sin θ + 30·cos θ = 13 mm (half the link thickness);
    then J2 freezes and the distal link closes on until it touches the bar's outer face."""
    res = results["breakaway_bar"]
    p = BH8_282
    theta = brentq(
        lambda t: (
            -(0.10 - p.base_to_proximal) * math.sin(t)
            + 0.03 * math.cos(t)
            - p.proximal_thickness / 2
        ),
        0.0,
        math.pi / 2,
    )
    j2, j3, stop = reference_close(rectangle(0.06, 0.10, 0.03, 0.06))
    assert j2 == pytest.approx(math.degrees(theta), abs=1e-6)  # the 2-D model agrees
    assert stop == "breakaway-distal"
    assert res.joint("f3_prox") == pytest.approx(j2, abs=ANGLE_TOL_DEG)
    assert res.joint("f3_dist") == pytest.approx(j3, abs=ANGLE_TOL_DEG)
    assert res.joint("f3_dist") > res.joint("f3_prox") / 3 + 20.0  # well past the coupling
    assert res.finger_stops == ("limit", "limit", "breakaway-distal")
    assert res.joints_deg.f1_prox == 140.0 and res.joints_deg.f1_dist == pytest.approx(140 / 3)
    assert res.dofs_deg.f3 == pytest.approx(3 * res.joint("f3_dist"))
    assert {c.link for c in res.contacts} == {"f3_prox", "f3_dist"}


def test_missed_object_closes_fully_and_fails_as_a_value(results):
    res = results["miss"]
    assert not res.success and res.reason.startswith("no contact")
    assert res.travel == pytest.approx(0.2)  # the whole max_travel
    np.testing.assert_allclose(res.joints_deg, [0, 140, 140 / 3, 0, 140, 140 / 3, 140, 140 / 3])
    assert res.contacts == () and res.epsilon == -1.0 and res.volume == 0.0


# -- invariances and regressions -------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1])
def test_rigid_motion_of_the_whole_scene_changes_nothing(seed, results):
    rng = np.random.default_rng(seed)
    motion = np.eye(4)
    motion[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    motion[:3, 3] = rng.uniform(-1.0, 1.0, 3)
    for name, scene in SCENES.items():
        mesh = scene.mesh.copy()
        mesh.apply_transform(motion)
        moved = autograsp(
            mesh, motion @ scene.palm_pose, spread_deg=scene.spread_deg, approach=scene.approach
        )
        base = results[name]
        np.testing.assert_allclose(
            moved.joints_deg, base.joints_deg, atol=ANGLE_TOL_DEG, err_msg=name
        )
        assert moved.travel == pytest.approx(base.travel, abs=1e-4), name
        np.testing.assert_allclose(moved.palm_pose, motion @ base.palm_pose, atol=1e-4)
        assert moved.finger_stops == base.finger_stops, name


def test_halving_the_steps_changes_nothing(results):
    for name, scene in SCENES.items():
        fine = grasp(scene, approach_step=0.005, close_step_deg=math.degrees(0.005))
        base = results[name]
        np.testing.assert_allclose(
            fine.joints_deg, base.joints_deg, atol=ANGLE_TOL_DEG, err_msg=name
        )
        assert fine.travel == pytest.approx(base.travel, abs=1e-4), name
        assert fine.finger_stops == base.finger_stops, name


def test_two_runs_are_identical(results):
    scene = SCENES["mug"]
    shared = CollisionScene(scene.mesh)
    runs = [grasp(scene), autograsp(shared, scene.palm_pose), autograsp(shared, scene.palm_pose)]
    for run in runs:
        assert run.joints_deg == results["mug"].joints_deg
        assert run.travel == results["mug"].travel
        assert run.epsilon == results["mug"].epsilon
        assert [c.link for c in run.contacts] == [c.link for c in results["mug"].contacts]


def test_larger_cylinder_closes_less():
    """Lying cylinders of growing radius: every closing joint and DOF strictly decreases."""
    grasps = [autograsp(lying_cylinder(r), START) for r in (0.025, 0.03, 0.035, 0.04, 0.045, 0.05)]
    closing = np.array([[g.joint(n) for n in JOINT_NAMES if "spread" not in n] for g in grasps])
    dofs = np.array([g.dofs_deg[1:] for g in grasps])
    assert np.all(np.diff(closing, axis=0) < -0.5)
    assert np.all(np.diff(dofs, axis=0) < -0.5)


def test_backs_off_when_starting_in_collision(results):
    """Starting 20 mm inside the box, the hand backs off and lands where it would have."""
    inside = START.copy()
    inside[2, 3] = 0.02
    res = autograsp(SCENES["box_long"].mesh, inside)
    assert res.travel < 0.0
    np.testing.assert_allclose(res.palm_pose, results["box_long"].palm_pose, atol=1e-4)
    np.testing.assert_allclose(res.joints_deg, results["box_long"].joints_deg, atol=ANGLE_TOL_DEG)


def test_stuck_hand_fails_as_a_value():
    """Inside a 3 m tube narrower than the palm, backing off 1 m never frees the hand."""
    tube = trimesh.creation.annulus(r_min=0.03, r_max=0.06, height=3.0, sections=32)
    res = autograsp(tube, np.eye(4))
    assert not res.success and "still in collision" in res.reason
    np.testing.assert_array_equal(res.palm_pose, np.eye(4))


def test_quality_can_be_added_later(results):
    scene = SCENES["sphere_tripod"]
    bare = grasp(scene, quality=False)
    assert bare.joints_deg == results["sphere_tripod"].joints_deg
    assert not bare.success and math.isnan(bare.epsilon) and bare.reason == "quality not computed"
    scored = with_quality(bare, CollisionScene(scene.mesh))
    full = results["sphere_tripod"]
    assert (scored.success, scored.reason, scored.epsilon, scored.volume) == (
        full.success,
        full.reason,
        full.epsilon,
        full.volume,
    )


# -- the joint-error protocol ----------------------------------------------------------------------
def test_regrasp_on_the_same_mesh_reproduces_the_grasp(results):
    for name in ("box_long", "cylinder_lying", "sphere_tripod"):
        first = results[name]
        again = regrasp(first, SCENES[name].mesh)
        mean, per_joint = joint_error_deg(first, again)
        assert per_joint.shape == (8,) and mean < ANGLE_TOL_DEG, name
        np.testing.assert_allclose(again.palm_pose, first.palm_pose, atol=1e-4)
        assert again.dofs_deg.spread == first.dofs_deg.spread


def test_regrasp_on_another_mesh_keeps_orientation_and_measures_the_difference(results):
    first = results["cylinder_lying"]
    fatter = regrasp(first, lying_cylinder(0.045))
    np.testing.assert_allclose(fatter.palm_pose[:3, :3], first.palm_pose[:3, :3], atol=1e-12)
    offset = fatter.palm_pose[:3, 3] - first.palm_pose[:3, 3]
    np.testing.assert_allclose(np.cross(offset, first.palm_pose[:3, 2]), 0.0, atol=1e-12)
    mean, per_joint = joint_error_deg(first, fatter)
    assert mean == pytest.approx(per_joint.mean())
    assert per_joint[0] == per_joint[3] == 0.0  # same spread
    assert np.all(per_joint[[1, 2, 4, 5, 6, 7]] > 1.0)
    np.testing.assert_allclose(
        pregrasp_pose(first.palm_pose, 0.2)[:3, 3],
        first.palm_pose[:3, 3] - 0.2 * first.palm_pose[:3, 2],
    )


# -- API -------------------------------------------------------------------------------------------
def test_result_access_by_name_and_json(results):
    res = results["sphere_tripod"]
    assert res.joint("f3_prox") == res.joints_deg.f3_prox == res.joints_deg[6]
    assert res.joints_deg._asdict()["f1_spread"] == 60.0 == res.dofs_deg.spread
    assert len(res.joints_deg) == 8 and len(res.dofs_deg) == 4
    data = json.loads(json.dumps(res.as_dict()))
    assert data["joints_deg"]["f2_dist"] == pytest.approx(res.joints_deg.f2_dist)
    for c in res.contacts:
        assert c.link in {"palm", "f1_dist", "f2_dist", "f3_prox", "f3_dist", "f1_prox", "f2_prox"}
        assert np.linalg.norm(c.normal) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="unknown joint"):
        res.joint("f4_prox")


def test_bad_input_raises():
    mesh = box((0.05, 0.05, 0.05), (0, 0, 0.1))
    with pytest.raises(ValueError, match="spread"):
        autograsp(mesh, np.eye(4), spread_deg=200.0)
    with pytest.raises(ValueError, match="max_travel"):
        autograsp(mesh, np.eye(4), max_travel=-1.0)
    with pytest.raises(ValueError, match="rigid"):
        autograsp(mesh, 2.0 * np.eye(4))
    with pytest.raises(ValueError, match="Trimesh"):
        autograsp("mesh.obj", np.eye(4))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="positive"):
        autograsp(mesh, np.eye(4), close_step_deg=0.0)


def test_grasp_modules_do_not_import_torch():
    code = (
        "import sys, grasp.hand.autograsp, grasp.planner, grasp.hand.quality, "
        "grasp.evaluate.picture, grasp.evaluate.render, "
        "hands.barrett.urdf; assert 'torch' not in sys.modules, 'torch imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=GOLDEN_PATH.parents[2])


def test_the_planner_does_not_import_pybullet():
    """The planner's workers use the fcl scene (grasp.hand.collision); pybullet is for pictures and
    physics (grasp.evaluate.picture, grasp.physics)."""
    code = ("import sys, grasp.planner, grasp.hand.autograsp, grasp.hand.collision, "
            "grasp.search.candidates, "
            "grasp.hand.quality; assert 'pybullet' not in sys.modules, 'pybullet imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=GOLDEN_PATH.parents[2])


def test_breakaway_scene_builder_is_the_golden_one():
    assert breakaway_bar().name in SCENES and not SCENES["breakaway_bar"].approach
    assert isinstance(SCENES["mug"].mesh, trimesh.Trimesh)
