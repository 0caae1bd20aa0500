"""grasp.planner: candidates around the object, ranked autograsps, deterministic from the seed."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from grasp_scenes import box
from scipy.spatial.transform import Rotation

from grasp.defaults import AUTOGRASP_BUDGET
from grasp.hand.autograsp import autograsp
from grasp.hand.collision import CollisionScene
from grasp.hand.table import crosses, hand_clearance, hand_points
from grasp.planner import plan
from grasp.ranking.rank import DISTINCT_DEG, DISTINCT_M, depth_of, distinct, palm_touches, rank_key
from grasp.search.candidates import STANDOFF_M, candidate_poses, principal_axes
from grasp.search.loop import SCREEN_SPACING_M
from grasp_client.wire import SupportPlane


@pytest.fixture(scope="module")
def brick() -> trimesh.Trimesh:
    """A 50 × 80 × 150 mm box, rotated and moved off the origin."""
    mesh = box((0.05, 0.08, 0.15), (0.0, 0.0, 0.0))
    motion = np.eye(4)
    motion[:3, :3] = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
    motion[:3, 3] = [0.3, -0.2, 0.5]
    mesh.apply_transform(motion)
    return mesh


@pytest.fixture(scope="module")
def brick_plan(brick):
    return plan(brick, n_candidates=32, seed=0, top_k=None, budget=None)


def test_principal_axes_of_a_box_are_its_edges(brick):
    axes = principal_axes(brick)
    rot = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
    # longest extent first: the 150 mm edge (box z), then 80 mm (y), then 50 mm (x)
    for axis, column in zip(axes, (2, 1, 0), strict=True):
        assert abs(np.dot(axis, rot[:, column])) == pytest.approx(1.0, abs=1e-9)
    assert np.linalg.det(axes) == pytest.approx(1.0)


def test_candidates_aim_at_the_object_from_outside(brick):
    cands = candidate_poses(brick, n_candidates=40, seed=3)
    assert len(cands) == 40
    assert [c.source for c in cands[:24]] == ["principal"] * 24
    assert {c.source for c in cands[24:]} == {"sphere"}
    center = brick.bounds.mean(axis=0)
    radius = np.linalg.norm(brick.vertices - center, axis=1).max()
    for c in cands:
        origin, approach = c.palm_pose[:3, 3], c.palm_pose[:3, 2]
        to_center = center - origin
        assert np.linalg.norm(to_center) == pytest.approx(radius + STANDOFF_M)
        np.testing.assert_allclose(np.cross(approach, to_center), 0.0, atol=1e-12)
        assert np.dot(approach, to_center) > 0.0
        np.testing.assert_allclose(
            c.palm_pose[:3, :3].T @ c.palm_pose[:3, :3], np.eye(3), atol=1e-12
        )
        assert 0.0 <= c.spread_deg <= 180.0
    # the principal candidates approach along ±each principal axis
    axes = principal_axes(brick)
    dots = np.abs([[np.dot(c.palm_pose[:3, 2], a) for a in axes] for c in cands[:24]])
    np.testing.assert_allclose(np.sort(dots, axis=1)[:, -1], 1.0, atol=1e-12)


def test_candidates_are_deterministic_from_the_seed(brick):
    a = candidate_poses(brick, n_candidates=30, seed=5)
    b = candidate_poses(brick, n_candidates=30, seed=5)
    c = candidate_poses(brick, n_candidates=30, seed=6)
    assert all(np.array_equal(x.palm_pose, y.palm_pose) for x, y in zip(a, b, strict=True))
    assert any(not np.array_equal(x.palm_pose, y.palm_pose) for x, y in zip(a, c, strict=True))
    # the seed only moves the random (sphere) candidates
    assert all(
        np.array_equal(x.palm_pose, y.palm_pose) for x, y in zip(a[:24], c[:24], strict=True)
    )


def test_plan_is_ranked_by_closure_palm_force_epsilon(brick_plan):
    assert len(brick_plan) == 32
    keys = [rank_key(r) for r in brick_plan]
    assert keys == sorted(keys, reverse=True)
    best = brick_plan[0]
    assert best.success and best.force_epsilon > 0.2 and best.reason == "force closure"
    power = [r for r in brick_plan if r.success and palm_touches(r)]
    assert power and palm_touches(best)  # a power grasp of the brick exists and comes first
    assert all(r.force_epsilon <= best.force_epsilon for r in power)
    assert all(r.force_epsilon >= r.epsilon for r in brick_plan if r.success)


def test_plan_is_deterministic_and_top_k_are_the_best_distinct(brick, brick_plan):
    """Without the screen, the lazily scored top-k are exactly the full ranking's first k
    distinct grasps."""
    again = plan(CollisionScene(brick), n_candidates=32, seed=0, top_k=5, budget=None)
    assert len(again) == 5
    for a, b in zip(again, distinct(brick_plan)[:5], strict=True):
        assert a.joints_deg == b.joints_deg
        np.testing.assert_array_equal(a.palm_pose, b.palm_pose)
        assert (a.epsilon, a.volume) == (b.epsilon, b.volume)


def test_screened_plan_autograsps_its_budget_and_returns_grasps_of_the_full_plan(brick, brick_plan):
    """With the screen, the budget's most promising candidates are autograsped, whatever top_k;
    what comes back is the same grasps the exact planner finds for those candidates, distinct
    and deterministic."""
    timings: dict[str, float] = {}
    top = plan(brick, n_candidates=32, seed=0, top_k=3, timings=timings)
    assert timings["screened"] == 32 and timings["autograsped"] == AUTOGRASP_BUDGET
    assert set(timings) >= {"setup", "screen", "autograsp", "rank"}
    assert len(top) == 3 and all(g.success for g in top)
    assert distinct(top) == top
    exact = {(r.palm_pose.tobytes(), r.dofs_deg.spread): r for r in brick_plan}
    for g in top:
        twin = exact[g.palm_pose.tobytes(), g.dofs_deg.spread]
        assert g.joints_deg == twin.joints_deg and g.force_epsilon == twin.force_epsilon
    again = plan(brick, n_candidates=32, seed=0, top_k=3)
    assert [g.joints_deg for g in again] == [g.joints_deg for g in top]
    # the screen puts the best of the full ranking among the candidates it autograsps
    assert top[0].force_epsilon >= 0.9 * brick_plan[0].force_epsilon
    few: dict[str, float] = {}
    plan(brick, n_candidates=32, seed=0, top_k=1, budget=5, timings=few)
    assert few["autograsped"] == 5


@pytest.mark.parametrize("table", [False, True])
def test_the_top_grasp_does_not_depend_on_top_k(table):
    """The search is the same whatever top_k asks: plan(top_k=1)[0] is plan(top_k=5)[0] (and
    the top_k=5 list starts the top_k=10 one), on random primitives, free or on a table."""
    rng = np.random.default_rng(11 + table)
    makers = [lambda e: trimesh.creation.box(e), lambda e: trimesh.creation.capsule(e[2], e[0] / 2),
              lambda e: trimesh.creation.cylinder(e[0] / 2, e[2]), lambda e: trimesh.creation.cone(
                  e[0] / 2, e[2]), lambda e: trimesh.creation.icosphere(2, e[0] / 2)]
    for k in range(10):
        extents = rng.uniform(0.02, 0.16, 3)
        mesh = makers[k % len(makers)](extents)
        mesh.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
        plane = None
        if table:
            mesh.apply_translation([0.0, 0.0, -mesh.bounds[0, 2]])
            plane = SupportPlane(np.array([0.0, 0.0, 1.0]), 0.0)
        one = plan(mesh, n_candidates=32, seed=k, top_k=1, support_plane=plane)
        five = plan(mesh, n_candidates=32, seed=k, top_k=5, support_plane=plane)
        ten = plan(mesh, n_candidates=32, seed=k, top_k=10, support_plane=plane)
        assert one[0].joints_deg == five[0].joints_deg, k
        np.testing.assert_array_equal(one[0].palm_pose, five[0].palm_pose)
        assert [g.joints_deg for g in five] == [g.joints_deg for g in ten[:len(five)]], k


def test_screen_predicts_where_the_approach_stops_and_what_touches(brick):
    from grasp.search.screen import Screen

    scene = CollisionScene(brick)
    candidates = candidate_poses(brick, n_candidates=32, seed=0)
    palms = np.stack([c.palm_pose for c in candidates])
    spreads = np.array([c.spread_deg for c in candidates])
    travel = float(np.linalg.norm(brick.extents)) + 2 * STANDOFF_M
    screen = Screen(brick, spacing=SCREEN_SPACING_M)
    touches, palm, depth = screen.predict(palms, spreads, travel, scene.center)
    agree = []
    for c, t, p, d in zip(candidates, touches, palm, depth, strict=True):
        exact = autograsp(scene, c.palm_pose, spread_deg=c.spread_deg, max_travel=travel)
        assert t == bool(exact.contacts)
        if t:
            assert abs(d - depth_of(exact, scene.center)) < 2.0 * screen.field.pitch
            agree.append(p == palm_touches(exact))
    assert np.mean(agree) >= 0.85


def test_failures_come_back_as_values():
    """A 60 cm cube is far too big for the hand: no exception, every result says why."""
    huge = trimesh.creation.box(extents=(0.6, 0.6, 0.6))
    results = plan(huge, n_candidates=6, top_k=None)
    assert len(results) == 6
    assert not any(r.success for r in results)
    assert all(r.reason.startswith("no force closure") for r in results)
    assert all(r.epsilon == -1.0 for r in results)


def test_bad_input_raises(brick):
    with pytest.raises(ValueError, match="n_candidates"):
        plan(brick, n_candidates=0)
    with pytest.raises(ValueError, match="top_k"):
        plan(brick, n_candidates=4, top_k=0)
    with pytest.raises(ValueError, match="spreads_deg"):
        candidate_poses(brick, spreads_deg=(0.0, 200.0))
    with pytest.raises(ValueError, match="Trimesh"):
        plan("brick.obj")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"the shape is 3.46 m across"):
        plan(trimesh.creation.box((2.0, 2.0, 2.0)), n_candidates=4)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def test_top_k_are_distinct_grasps():
    """A cube's symmetric candidates land on the same palm poses; top-k never repeats one."""
    cube = trimesh.creation.box(extents=(0.06, 0.06, 0.12))
    top = plan(cube, n_candidates=64, seed=0, top_k=6, budget=None)
    assert len(top) == 6
    for i, a in enumerate(top):
        for b in top[:i]:
            far = np.linalg.norm(a.palm_pose[:3, 3] - b.palm_pose[:3, 3]) >= DISTINCT_M
            assert far or _angle_deg(a.palm_pose, b.palm_pose) >= DISTINCT_DEG
    everything = plan(cube, n_candidates=64, seed=0, top_k=None, budget=None)
    assert len(distinct(everything)) < len(everything)  # there were duplicates to leave out


@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (0.3, -0.2, 1.0)])
def test_support_plane_no_approach_from_below_no_hand_below(brick, normal):
    """The brick rests on a plane through its lowest corner (the table): no returned grasp comes
    from below, and no link of the hand reaches below the plane."""
    n = np.asarray(normal) / np.linalg.norm(normal)
    plane = SupportPlane(n, -float((brick.vertices @ n).min()))
    assert plane.height(brick.vertices).min() == pytest.approx(0.0, abs=1e-12)
    grasps = plan(brick, n_candidates=48, seed=0, top_k=10, support_plane=plane)
    assert grasps and grasps[0].success
    for g in grasps:
        assert g.palm_pose[:3, 2] @ plane.normal <= 1e-9  # approach along or down the plane
        assert plane.height(hand_points(g)).min() >= -1e-9
        assert hand_clearance(plane, g) >= -1e-9 and not crosses(plane, g)
    free = plan(brick, n_candidates=48, seed=0, top_k=10)
    assert any(g.palm_pose[:3, 2] @ plane.normal > 0.1 or crosses(plane, g) for g in free)


def test_support_plane_parsing_and_frames():
    plane = SupportPlane.parse("0,0,2,-1")  # z = 0.5, normalised
    np.testing.assert_allclose(plane.normal, [0, 0, 1])
    assert plane.offset == pytest.approx(-0.5)
    lifted = np.eye(4)
    lifted[:3, 3] = [0.0, 0.0, 0.2]  # a frame 0.2 m above this one
    assert plane.transformed(lifted).height(np.zeros((1, 3)))[0] == pytest.approx(-0.3)
    for bad in ("0,0,1", "a,b,c,d", "0,0,0,1"):
        with pytest.raises(ValueError):
            SupportPlane.parse(bad)


@pytest.mark.parametrize("object_id", ["named/duck", "named/mug", "proc/box/3"])
def test_fast_screen_agrees_with_the_exact_check_on_free_poses(object_id):
    """On many random palm poses around the object, the distance-field screen and the exact
    fcl check agree on whether the open hand is clear; where they differ, the hand is within
    about a voxel of touching, and the screen never calls a colliding pose free."""
    from completion.objects import load_object
    from grasp.search.candidates import _random_rotation
    from grasp.search.screen import Screen

    mesh = load_object(object_id)
    screen = Screen(mesh)
    scene = CollisionScene(mesh)
    rng = np.random.default_rng(0)
    palms = np.tile(np.eye(4), (200, 1, 1))
    for palm in palms:
        palm[:3, :3] = _random_rotation(rng)
        palm[:3, 3] = mesh.bounds.mean(axis=0) + rng.normal(scale=0.06, size=3)
    spreads = rng.choice([0.0, 30.0, 60.0, 90.0], len(palms))
    clearance = screen.clearance(palms, spreads)
    exact = []
    for palm, spread in zip(palms, spreads, strict=True):
        joints = np.zeros(8)
        joints[[0, 3]] = np.radians(spread)
        exact.append(not scene.hand_collides(palm, joints))
    exact = np.array(exact)
    fast = clearance > 0
    assert 0.05 < exact.mean() < 0.95  # both kinds of pose were tried
    assert (fast == exact).mean() >= 0.97
    assert not np.any(fast & ~exact)
    assert np.abs(clearance[fast != exact]).max(initial=0.0) <= 1.5 * screen.field.pitch


def test_fast_approach_stops_at_the_exact_contact():
    from grasp.search.screen import Screen

    cube = trimesh.creation.box(extents=(0.06, 0.06, 0.06))
    screen = Screen(cube)
    palms = np.stack([c.palm_pose for c in candidate_poses(cube, n_candidates=24, seed=0)])
    spreads = np.zeros(len(palms))
    travel = screen.approach(palms, spreads, max_travel=0.3)
    for palm, t in zip(palms, travel, strict=True):
        exact = autograsp(cube, palm, spread_deg=0.0, max_travel=0.3, quality=False)
        assert abs(t - exact.travel) < 1.5 * screen.field.pitch


def test_a_sheet_of_two_triangles_is_planned_on():
    """Principal axes of a mesh with fewer faces than dimensions (a regression: the SVD gave
    two axes and the planner raised IndexError)."""
    sheet = trimesh.Trimesh(
        [[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0.05, 0.05, 0]], [[0, 1, 2], [1, 3, 2]]
    )
    axes = principal_axes(sheet)
    np.testing.assert_allclose(axes @ axes.T, np.eye(3), atol=1e-9)
    grasps = plan(sheet, n_candidates=16, top_k=1)
    assert len(grasps) == 1 and grasps[0].contacts
