"""Neighbours as obstacles (grasp.search.obstacles, issue 61): voxels the hand keeps clear of while
it approaches and closes, the planner refusing grasps that would touch them, and the lift test
with the neighbours as dynamic bodies on the table."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from grasp.physics.lift import lift_test
from grasp.planner import plan
from grasp.search.obstacles import Obstacles, sweep_hit
from grasp_client.wire import SupportPlane

TABLE = SupportPlane([0.0, 0.0, 1.0], 0.0)


def standing_box(extents, at) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents)
    box.apply_translation([at[0], at[1], extents[2] / 2])
    return box


@pytest.fixture(scope="module")
def target():
    return standing_box((0.06, 0.06, 0.12), (0.0, 0.0))


@pytest.fixture(scope="module")
def neighbour():
    """A box like the target, 3 cm beside it: in the way of the fingers of its best grasp."""
    return standing_box((0.06, 0.06, 0.12), (0.0, 0.09))


def test_obstacle_points_snap_to_voxels_so_views_of_one_surface_add_nothing_twice():
    rng = np.random.default_rng(0)
    points = rng.uniform(0.0, 0.05, size=(2000, 3))
    once = Obstacles.from_points(points, pitch=0.01)
    twice = Obstacles.from_points(np.concatenate([points, points + 1e-4]), pitch=0.01)
    assert len(once) <= 125 and len(twice) <= len(once) + 25  # a 5 cm cube of 1 cm voxels
    assert np.allclose(np.sort(Obstacles(once.centres, 0.01).centres, axis=0),
                       np.sort(once.centres, axis=0))
    shifted = once.transformed(np.array([[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0],
                                         [0, 0, 0, 1.0]]))
    assert np.isclose(shifted.centres[:, 0].min(), once.centres[:, 0].min() + 0.1)
    with pytest.raises(ValueError, match="pitch"):
        Obstacles.from_points(points, pitch=0.0)
    with pytest.raises(ValueError, match="finite"):
        Obstacles.from_points(np.array([[0.0, np.nan, 0.0]]))


def test_the_sweep_finds_obstacles_on_the_way_in_and_while_closing(target, neighbour):
    top = plan(target, n_candidates=64, seed=0, top_k=1, support_plane=TABLE)[0]
    start = top.palm_pose.copy()
    start[:3, 3] -= 0.15 * top.palm_pose[:3, 2]  # 15 cm back along the approach
    behind = standing_box((0.04, 0.04, 0.04), start[:3, 3][:2] - [0, 0])  # on the path in
    behind.apply_translation([0, 0, start[2, 3] - 0.02])
    hit = sweep_hit(Obstacles.from_meshes([behind]), start, top.palm_pose, top.joints_deg)
    assert hit is not None and hit.phase == "approach"
    # the neighbour is clear of the open hand at its pre-grasp but in its fingers' way
    hit = sweep_hit(Obstacles.from_meshes([neighbour]), top.palm_pose, top.palm_pose,
                    top.joints_deg)
    assert hit is not None and hit.link != "palm"
    far = standing_box((0.06, 0.06, 0.12), (0.6, 0.6))
    assert sweep_hit(Obstacles.from_meshes([far]), start, top.palm_pose, top.joints_deg) is None
    assert sweep_hit(None, start, top.palm_pose, top.joints_deg) is None


def test_without_obstacles_the_plan_is_unchanged(target):
    plain = plan(target, n_candidates=32, seed=1, top_k=3, support_plane=TABLE)
    for none in (None, Obstacles(np.zeros((0, 3)))):
        same = plan(target, n_candidates=32, seed=1, top_k=3, support_plane=TABLE, obstacles=none)
        assert [g.reason for g in same] == [g.reason for g in plain]
        assert all(np.array_equal(a.palm_pose, b.palm_pose) for a, b in zip(same, plain,
                                                                             strict=True))


def test_the_planner_picks_another_grasp_where_the_best_one_sweeps_through_a_neighbour(
        target, neighbour):
    """Issue 61's hand-built scene: the best grasp without obstacles pushes the neighbour 3 cm
    away (it moves > 2 cm in the lift test); with the neighbour as an obstacle the planner
    returns another grasp, which holds and leaves the neighbour where it stood."""
    ignoring = plan(target, n_candidates=64, seed=0, top_k=1, support_plane=TABLE)[0]
    obstacles = Obstacles.from_meshes([neighbour])
    avoiding = plan(target, n_candidates=64, seed=0, top_k=3, support_plane=TABLE,
                    obstacles=obstacles)
    best = avoiding[0]
    assert best.success and not np.allclose(best.palm_pose, ignoring.palm_pose)
    assert sweep_hit(obstacles, best.palm_pose, best.palm_pose, best.joints_deg) is None
    pushed = lift_test(target, ignoring, seed=0, support_plane=TABLE, approach="guarded",
                       neighbours=[neighbour])
    assert pushed.neighbour_moved > 0.02
    clear = lift_test(target, best, seed=0, support_plane=TABLE, approach="guarded",
                      neighbours=[neighbour])
    assert clear.success and clear.neighbour_moved < 0.005 and clear.neighbour_tilt_deg < 2.0


def test_a_target_boxed_in_gets_no_grasp_and_the_reason_names_the_obstacles(target):
    walls = [standing_box((0.3, 0.02, 0.3), (0.0, 0.05)), standing_box((0.3, 0.02, 0.3),
                                                                       (0.0, -0.05)),
             standing_box((0.02, 0.3, 0.3), (0.05, 0.0)), standing_box((0.02, 0.3, 0.3),
                                                                       (-0.05, 0.0))]
    walls += [standing_box((0.3, 0.3, 0.02), (0.0, 0.0))]
    walls[-1].apply_translation([0, 0, 0.14])  # a lid 2 cm above the target
    best = plan(target, n_candidates=32, seed=0, top_k=1, support_plane=TABLE,
                obstacles=Obstacles.from_meshes(walls))[0]
    assert not best.success
    assert "would hit an obstacle" in best.reason or "blocked at the pre-grasp" in best.reason
    assert "obstacles:" in best.reason


def test_a_preshaped_hand_approaches_with_its_fingers_half_closed_and_closes_from_there(target):
    from grasp.hand.autograsp import autograsp

    down = np.eye(4)
    down[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]  # palm +z pointing down
    down[:3, 3] = [0.0, 0.0, 0.35]
    g = autograsp(target, down, spread_deg=0.0, max_travel=0.3, preshape_deg=45.0,
                  support_plane=TABLE)
    assert g.preshape_deg == 45.0 and min(g.dofs_deg[1:]) >= 45.0
    assert "preshape_deg" in g.as_dict()
    with pytest.raises(ValueError, match="preshape_deg"):
        autograsp(target, down, preshape_deg=150.0)


def test_among_neighbours_the_planner_preshapes_the_hand_where_the_open_one_would_touch():
    """The clutter table's scene 4 (a 15 × 15 × 5 cm box among 4 neighbours): no open-hand
    grasp is clear of them (the planner's best open-hand grasps touch one); the top grasp
    approaches with the fingers at 45°, holds, and leaves the neighbours standing (the lift
    test executes the pre-shape)."""
    from grasp.evaluate.clutter_scenes import scene_objects
    from grasp.hand.autograsp import pregrasp_pose
    from grasp.search.loop import CLUTTER_PRESHAPE_DEG

    _, target, _, neighbours, _, _ = scene_objects(4, 0)
    obstacles = Obstacles.from_meshes(neighbours)
    best = plan(target, n_candidates=64, seed=0, top_k=1, support_plane=TABLE,
                obstacles=obstacles)[0]
    assert best.success and best.preshape_deg == CLUTTER_PRESHAPE_DEG
    start = pregrasp_pose(best.palm_pose, 0.1)  # 10 cm back along the approach
    assert sweep_hit(obstacles, start, best.palm_pose, best.joints_deg,
                     preshape_deg=best.preshape_deg) is None
    result = lift_test(target, best, seed=0, support_plane=TABLE, approach="guarded",
                       neighbours=neighbours)
    assert result.success and result.neighbour_moved < 0.005
    prox = result.joints_deg[[1, 4, 6]]  # f1, f2, f3 proximal joints, executed
    assert (prox >= CLUTTER_PRESHAPE_DEG - 2.0).all()


def test_the_batched_pregrasp_check_agrees_with_the_sweep_of_a_hand_standing_still(target,
                                                                                   neighbour):
    """:func:`hand_clear` (every candidate at once, what the planner checks its pre-grasps with)
    gives what :func:`sweep_hit` gives for a hand that does not move, open and pre-shaped."""
    from grasp.search.candidates import table_candidates
    from grasp.search.obstacles import hand_clear
    from hands.barrett.kinematics import joints_from_dofs

    obstacles = Obstacles.from_meshes([neighbour, standing_box((0.05, 0.2, 0.1), (-0.1, 0.0))])
    candidates = table_candidates(target, TABLE, travel=0.4, n_candidates=64, seed=0)
    palms = np.stack([c.palm_pose for c in candidates])
    spreads = np.array([c.spread_deg for c in candidates])
    for shape in (0.0, 45.0):
        batched = hand_clear(obstacles, palms, spreads, shape)
        one_by_one = [sweep_hit(obstacles, c.palm_pose, c.palm_pose,
                                joints_from_dofs([c.spread_deg, *[shape] * 3]),
                                preshape_deg=shape) is None for c in candidates]
        assert batched.tolist() == one_by_one
        assert 0 < batched.sum() < len(candidates)  # the scene blocks some, not all
    assert hand_clear(None, palms, spreads).all()

