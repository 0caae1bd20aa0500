"""The table as an obstacle (docs/design.md §7, "Support plane"): autograsp, screen and planner.

Hand-computed cases use only the hand's dimensions (hands/barrett/params.py, BARRETT.md): J2 axes
on the palm face 50 mm out, proximal link 70 mm (26 mm thick), distal link 55 mm (20 mm thick)
bent 40° inward, J3 = J2 / 3 while a finger closes freely. In a finger's plane, with r outward
and z the depth below the palm face, the distal link's deepest point is its tip's outer corner:
z = 70 sin J2 + 55 sin φ + 10 cos φ, φ = J2 + 40° + J3 (for φ < 90°).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from grasp.hand.autograsp import autograsp
from grasp.hand.collision import CollisionScene
from grasp.hand.pinch import pinch_height
from grasp.hand.table import TABLE_TOL_M, hand_clearance, hand_primitives
from grasp.planner import plan
from grasp.search.candidates import TABLE_CLEARANCE_M, table_candidates
from grasp.search.screen import Screen, finger_reach, open_hand_lowest
from grasp_client.wire import SupportPlane

FLOOR = SupportPlane(np.array([0.0, 0.0, 1.0]), 0.0)  # the table z = 0
BEND = math.radians(40.0)


def distal_depth(j2: float, j3: float) -> float:
    """Depth (m) below the palm face of a finger's deepest distal point (radians in)."""
    phi = j2 + BEND + j3
    return 0.070 * math.sin(j2) + 0.055 * math.sin(phi) + 0.010 * math.cos(phi)


def palm_down(height: float, yaw_deg: float = 0.0) -> np.ndarray:
    """Palm face ``height`` above z = 0, approach straight down, turned ``yaw_deg`` about z."""
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("zx", [yaw_deg, 180.0], degrees=True).as_matrix()
    pose[2, 3] = height
    return pose


def far_cube() -> trimesh.Trimesh:
    """A 2 cm cube half a metre away: under no finger."""
    return trimesh.creation.box((0.02, 0.02, 0.02), trimesh.transformations.translation_matrix(
        [0.5, 0.5, 0.01]))


def lowest_point(plane: SupportPlane, grasp) -> float:
    """Height above ``plane`` of the lowest vertex of the hand's primitives as trimesh meshes
    (cylinders with 256 sections: within 0.01 mm of the true shape)."""
    low = np.inf
    for _, kind, size, pose in hand_primitives(grasp):
        if kind == "box":
            mesh = trimesh.creation.box(extents=size, transform=pose)
        else:
            mesh = trimesh.creation.cylinder(size[0], size[1], sections=256, transform=pose)
        low = min(low, float(plane.height(mesh.vertices).min()))
    return low


def resting(kind: str, rng: np.random.Generator) -> trimesh.Trimesh:
    """A primitive of random size, upright or on its side, random yaw, resting on z = 0."""
    if kind == "box":
        mesh = trimesh.creation.box(extents=rng.uniform(0.02, 0.12, 3))
    elif kind == "cylinder":
        mesh = trimesh.creation.cylinder(rng.uniform(0.015, 0.05), rng.uniform(0.02, 0.15),
                                         sections=32)
    elif kind == "capsule":
        mesh = trimesh.creation.capsule(rng.uniform(0.02, 0.1), rng.uniform(0.015, 0.04))
    elif kind == "cone":
        mesh = trimesh.creation.cone(rng.uniform(0.02, 0.05), rng.uniform(0.03, 0.12),
                                     sections=32)
    else:
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=rng.uniform(0.02, 0.06))
    tilt = 90.0 * rng.integers(0, 2)
    turn = Rotation.from_euler("zx", [rng.uniform(0.0, 360.0), tilt], degrees=True).as_matrix()
    mesh.apply_transform(np.block([[turn, np.zeros((3, 1))], [np.zeros((1, 3)), 1.0]]))
    mesh.apply_translation([*-mesh.bounds.mean(axis=0)[:2], -mesh.bounds[0, 2]])
    return mesh


def moved(mesh: trimesh.Trimesh, rng: np.random.Generator):
    """The mesh and the table z = 0 under one random rigid motion, and the motion (4, 4)."""
    motion = np.eye(4)
    motion[:3, :3] = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    motion[:3, 3] = rng.uniform(-0.5, 0.5, 3)
    mesh = mesh.copy()
    mesh.apply_transform(motion)
    return mesh, FLOOR.transformed(np.linalg.inv(motion)), motion


def low_box() -> trimesh.Trimesh:
    """8 × 5 × 3 cm box lying on z = 0, turned 30° about z."""
    box = trimesh.creation.box((0.08, 0.05, 0.03))
    box.apply_transform(trimesh.transformations.rotation_matrix(math.radians(30.0), [0, 0, 1]))
    box.apply_translation([0.02, -0.01, 0.015])
    return box


# -- autograsp: a finger that reaches the table stops there ---------------------------------------
@pytest.mark.parametrize("spread", [0.0, 90.0])
def test_fingers_closing_onto_the_table_stop_where_the_distal_tip_touches_it(spread):
    """Palm face 90 mm above the table, facing it, nothing under the fingers: each finger closes
    freely until its distal tip's outer corner reaches the table, 70 sin q + 55 sin φ + 10 cos φ
    = 90 mm with φ = 40° + 4q/3: q = 29.157°. The table is no grasp contact."""
    q = math.degrees(brentq(lambda q: distal_depth(q, q / 3) - 0.09, 0.0, 1.0))
    assert q == pytest.approx(29.157, abs=1e-3)
    res = autograsp(far_cube(), palm_down(0.09, 20.0), spread_deg=spread, approach=False,
                    support_plane=FLOOR)
    for finger in ("f1", "f2", "f3"):
        assert res.joint(f"{finger}_prox") == pytest.approx(q, abs=0.01)
        assert res.joint(f"{finger}_dist") == pytest.approx(q / 3, abs=0.01)
    assert res.finger_stops == ("distal",) * 3
    assert res.contacts == () and not res.success
    assert lowest_point(FLOOR, res) >= -1e-9


def test_approach_stops_when_the_open_hand_touches_the_table():
    """Coming down on an empty table, the open fingers' distal tips (bent 40°) lead:
    the palm face stops 55 sin 40° + 10 cos 40° = 43.01 mm above the table."""
    res = autograsp(far_cube(), palm_down(0.3), max_travel=0.5, support_plane=FLOOR)
    assert res.palm_pose[2, 3] == pytest.approx(distal_depth(0.0, 0.0), abs=2e-5)
    assert res.travel == pytest.approx(0.3 - distal_depth(0.0, 0.0), abs=2e-5)
    np.testing.assert_allclose(res.joints_deg, 0.0, atol=0.01)  # touching at once: no closing
    assert lowest_point(FLOOR, res) >= -1e-9
    # the screen sees the table too (the distal tips' corners are points of its cloud)
    screen = Screen(far_cube(), support_plane=FLOOR)
    assert screen.approach(palm_down(0.3)[None], np.zeros(1), 0.5)[0] == pytest.approx(
        res.travel, abs=1.5e-3)


def test_breakaway_onto_the_table():
    """The breakaway bar of tests/grasp_scenes.py upside down over a table 76.5 mm below the
    palm face. Finger 3's proximal link stops on the bar where 50 sin θ = 30 cos θ − 13 (mm):
    θ = 18.08°; then its distal link closes on alone (breakaway) and stops on the table:
    70 sin θ + 55 sin φ + 10 cos φ = 76.5 mm, J3 = φ − θ − 40° = 10.09°. Fingers 1 and 2 close
    freely onto the table: the equation of the test above at 76.5 mm, 18.70°."""
    depth = 0.0765
    theta = brentq(lambda t: 0.05 * math.sin(t) - 0.03 * math.cos(t) + 0.013, 0.0, 1.0)
    phi = brentq(lambda p: distal_depth(theta, p - theta - BEND) - depth,
                 theta + BEND + theta / 3, math.atan2(55, 10))
    free = brentq(lambda q: distal_depth(q, q / 3) - depth, 0.0, 1.0)
    bar = trimesh.creation.box((0.06, 0.04, 0.03))  # depth 30-60 mm, 60-100 mm from the centre
    bar.apply_translation([0.0, 0.08, depth - 0.045])
    res = autograsp(bar, palm_down(depth), approach=False, support_plane=FLOOR)
    assert res.joint("f3_prox") == pytest.approx(math.degrees(theta), abs=0.01)
    # the distal tip meets the table near its deepest swing, where 1 µm is 0.005°
    assert res.joint("f3_dist") == pytest.approx(math.degrees(phi - theta - BEND), abs=0.05)
    for finger in ("f1", "f2"):
        assert res.joint(f"{finger}_prox") == pytest.approx(math.degrees(free), abs=0.01)
    assert res.finger_stops == ("distal", "distal", "breakaway-distal")
    assert [c.link for c in res.contacts] == ["f3_prox"]  # the bar; the table is not a contact
    assert lowest_point(FLOOR, res) >= -1e-9


def test_table_grasps_do_not_depend_on_where_the_scene_is():
    """The same hand-built scene, tilted table and all, under a rigid motion: same joints."""
    base = autograsp(far_cube(), palm_down(0.09), approach=False, support_plane=FLOOR)
    mesh, plane, motion = moved(far_cube(), np.random.default_rng(3))
    res = autograsp(CollisionScene(mesh, support_plane=plane), motion @ palm_down(0.09),
                    approach=False)
    np.testing.assert_allclose(res.joints_deg, base.joints_deg, atol=0.01)


def test_autograsp_never_ends_below_the_table():
    """Random open hands above the table, approaching along or down it, on random objects:
    the final hand is never below the table."""
    rng = np.random.default_rng(0)
    for kind in ("box", "cylinder", "sphere", "cone"):
        mesh = resting(kind, rng)
        scene = CollisionScene(mesh, support_plane=FLOOR)
        for _ in range(10):
            z = rng.normal(size=3)
            z[2] = -abs(z[2])
            pose = np.eye(4)
            pose[:3, :3] = Rotation.align_vectors([z], [[0.0, 0.0, 1.0]])[0].as_matrix()
            pose[:3, :3] = pose[:3, :3] @ Rotation.from_euler("z", rng.uniform(0, 360),
                                                              degrees=True).as_matrix()
            pose[:3, 3] = -0.15 * z / np.linalg.norm(z) + [0.0, 0.0, 0.05]
            spread = float(rng.choice([0.0, 60.0, 90.0]))
            clear = open_hand_lowest(FLOOR, pose[None], np.array([spread]))[0]
            pose[2, 3] += max(0.0, 0.002 - clear)  # start clear of the table
            res = autograsp(scene, pose, spread_deg=spread, max_travel=0.3, quality=False)
            assert hand_clearance(FLOOR, res) >= -TABLE_TOL_M, kind
            assert lowest_point(FLOOR, res) >= -1e-3, kind


# -- candidates ----------------------------------------------------------------------------------
def test_table_candidates_top_down_and_fingertip_none_from_below_all_clear():
    box = low_box()
    cands = table_candidates(box, FLOOR, n_candidates=40, seed=0)
    assert len(cands) == 40
    assert [c.source for c in cands[:12]] == ["top"] * 4 + ["table pinch"] * 4 + ["pinch"] * 4
    for c in cands[:12]:
        np.testing.assert_allclose(c.palm_pose[:3, 2], [0.0, 0.0, -1.0], atol=1e-12)
    for c in cands[4:8]:  # table pinches: the open hand stops 2 mm above the table
        stop = c.palm_pose[2, 3] - c.travel
        assert stop == pytest.approx(pinch_height(), abs=1e-12)
    for c in cands[8:12]:  # the palm stops where the closing tips sweep just over the table
        stop = c.palm_pose[2, 3] - c.travel
        assert stop == pytest.approx(finger_reach() + 0.004, abs=1e-12)
    assert finger_reach() == pytest.approx(0.1136, abs=1e-4)
    palms = np.stack([c.palm_pose for c in cands])
    assert np.all(palms[:, :3, 2] @ FLOOR.normal <= 1e-9)  # none from below
    spreads = np.array([c.spread_deg for c in cands])
    assert open_hand_lowest(FLOOR, palms, spreads).min() >= TABLE_CLEARANCE_M - 1e-9
    again = table_candidates(box, FLOOR, n_candidates=40, seed=0)
    assert all(np.array_equal(a.palm_pose, b.palm_pose) for a, b in zip(cands, again,
                                                                         strict=True))
    tall = trimesh.creation.box((0.06, 0.06, 0.2))
    tall.apply_translation([0.0, 0.0, 0.1])
    assert not {"pinch", "table pinch"} & {c.source for c in table_candidates(tall, FLOOR,
                                                                             n_candidates=40)}


# -- the planner -----------------------------------------------------------------------------------
def test_no_planned_grasp_reaches_below_the_table_on_random_objects():
    """Primitives of many sizes, upright or lying, random yaw, on a table anywhere in space:
    no returned hand is below it (lowest vertex of its primitives, 1 mm), none comes from below,
    and almost every object gets a force-closure grasp."""
    rng = np.random.default_rng(7)
    found = []
    for kind in ("box", "cylinder", "capsule", "cone", "sphere") * 2:
        mesh, plane, _ = moved(resting(kind, rng), rng)
        grasps = plan(mesh, n_candidates=32, top_k=3, support_plane=plane)
        found.append(bool(grasps) and grasps[0].success)
        for g in grasps:
            assert g.palm_pose[:3, 2] @ plane.normal <= 1e-9, kind
            assert lowest_point(plane, g) >= -1e-3, kind
            assert hand_clearance(plane, g) >= -TABLE_TOL_M, kind
    assert sum(found) >= 8, found


def test_a_low_box_gets_a_top_down_grasp_that_lifts_it_off_the_table():
    from grasp.physics.lift import lift_test

    box = low_box()
    grasps = plan(box, n_candidates=64, top_k=10, support_plane=FLOOR)
    assert grasps[0].success  # the service's top-1
    top_down = [g for g in grasps if g.success and g.palm_pose[2, 2] < -0.99]
    assert top_down
    grasp = top_down[0]
    assert len(grasp.contacts) >= 3 and lowest_point(FLOOR, grasp) >= -1e-3
    lifted = lift_test(box, grasp, support_plane=FLOOR)
    assert lifted.success, lifted.reason


def test_a_standing_cylinder_gets_a_grasp():
    cylinder = trimesh.creation.cylinder(radius=0.03, height=0.10, sections=64)
    cylinder.apply_translation([0.0, 0.0, 0.05])
    grasps = plan(cylinder, n_candidates=64, top_k=3, support_plane=FLOOR)
    assert grasps and grasps[0].success
    assert all(lowest_point(FLOOR, g) >= -1e-3 for g in grasps)


def test_a_scene_built_with_a_table_plans_on_it():
    box = low_box()
    given = plan(box, n_candidates=24, top_k=2, support_plane=FLOOR)
    built = plan(CollisionScene(box, support_plane=FLOOR), n_candidates=24, top_k=2)
    assert [g.joints_deg for g in built] == [g.joints_deg for g in given]
    assert all(np.array_equal(a.palm_pose, b.palm_pose) for a, b in zip(built, given,
                                                                         strict=True))


def test_a_grasp_predicted_to_drop_comes_back_when_the_caller_asks():
    """A small flat object of the benchmark (urdf/988, 6 × 8 × 2 cm): its best force-closure
    grasp has a hold probability of about 0.43, refused by default (the reason says so);
    ``min_hold=0.3`` returns the same grasp with its probability, the rest unchanged."""
    from grasp.evaluate.benchmark_scenes import TABLE_PLANE, benchmark_objects, resting_object

    index = benchmark_objects(100, 0).index("urdf/988")
    mesh = resting_object("urdf/988", index, 0)[0]
    refused = plan(mesh, n_candidates=64, seed=0, top_k=1, support_plane=TABLE_PLANE)[0]
    asked = plan(mesh, n_candidates=64, seed=0, top_k=1, support_plane=TABLE_PLANE,
                 min_hold=0.3)[0]
    assert not refused.success and "predicted to drop when lifted" in refused.reason
    assert asked.success and 0.3 <= asked.hold_probability < 0.5
    assert asked.hold_probability == refused.hold_probability
    np.testing.assert_array_equal(asked.palm_pose, refused.palm_pose)
    with pytest.raises(ValueError, match="min_hold must be a probability"):
        plan(mesh, top_k=1, support_plane=TABLE_PLANE, min_hold=1.5)
