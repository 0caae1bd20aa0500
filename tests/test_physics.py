"""Tests of grasp/physics.py: the lift-and-shake check of a grasp in pybullet dynamics.

One box, grasped from the side: the palm approaches along world +x, the fingers oppose along
world y, so gravity pulls along the fingers' contact faces and only friction holds the box (the
palm cannot carry it). Each lift test takes about a second of simulation on one core.
"""

from __future__ import annotations

import numpy as np
import pybullet
import pytest
import trimesh

from grasp.cli import main as grasp_main
from grasp.hand.autograsp import autograsp
from grasp.physics.body import convex_decomposition, mass_properties
from grasp.physics.lift import lift_test
from grasp.physics.settings import HOLD_TOLERANCE_M, LiftResult, LiftSettings
from grasp.physics.world import DynamicWorld

BOX_EXTENTS = (0.06, 0.05, 0.08)  # along the approach, across the fingers, vertical (m)


def side_pose(position) -> np.ndarray:
    """Palm pose with the approach (+z) along world +x and the finger opposition (+y) along y."""
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = [0, 0, -1], [0, 1, 0], [1, 0, 0]
    pose[:3, 3] = position
    return pose


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("convex")


@pytest.fixture(scope="module")
def box():
    return trimesh.creation.box(extents=BOX_EXTENTS)


@pytest.fixture(scope="module")
def good_grasp(box):
    grasp = autograsp(box, side_pose([-0.15, 0.0, 0.0]), spread_deg=0.0)
    assert grasp.success, grasp.reason
    return grasp


@pytest.fixture(scope="module")
def held(box, good_grasp, cache) -> LiftResult:
    return lift_test(box, good_grasp, seed=3, cache_dir=cache)


def test_good_grasp_holds_the_box_through_lift_and_shake(held):
    assert held.success, held.reason
    assert held.phase == "held"
    assert held.slip <= HOLD_TOLERANCE_M
    assert held.displacement <= held.slip + 1e-12
    settings = LiftSettings()
    loaded = 0.25 + 0.10 / 0.10 + 0.25 + 4 / 3.0 + 0.25  # settle, lift, hold, shakes, hold
    assert held.total_s == pytest.approx(loaded, abs=2 * settings.time_step)
    assert held.held_s == held.total_s
    assert held.mass == pytest.approx(500.0 * np.prod(BOX_EXTENTS))
    assert held.contacts >= 3
    # every finger closed on the box: none reached its limit untouched
    assert all(stop != "limit" for stop in held.finger_stops)
    assert held.joints_deg.shape == (8,)
    assert 60.0 < held.joints_deg[1] < 120.0  # f1_prox near autograsp's ~101°


def test_lift_test_is_deterministic(box, good_grasp, held, cache):
    again = lift_test(box, good_grasp, seed=3, cache_dir=cache)
    assert again.displacement == held.displacement
    np.testing.assert_array_equal(again.offset, held.offset)
    assert again.slip == held.slip
    assert again.as_dict() == held.as_dict()
    # the seed picks the shake directions, so another seed shakes the box differently
    other = lift_test(box, good_grasp, seed=4, cache_dir=cache)
    assert other.displacement != held.displacement


def test_slippery_hand_drops_what_the_rubber_hand_holds(box, good_grasp, held, cache):
    slippery = lift_test(box, good_grasp, seed=3, friction=0.01, cache_dir=cache)
    assert held.success
    assert not slippery.success
    assert slippery.contacts >= 3  # the fingers did close on the box
    assert slippery.slip > HOLD_TOLERANCE_M
    assert slippery.held_s < held.held_s
    assert "left the hand" in slippery.reason


def test_hand_closing_beside_the_object_fails(box, cache):
    # 15 cm above the box, palm facing the same way: the fingers close on air
    beside = autograsp(box, side_pose([-0.031, 0.0, 0.15]), spread_deg=0.0, approach=False)
    assert not beside.success
    result = lift_test(box, beside, cache_dir=cache)
    assert not result.success
    assert result.contacts == 0
    assert result.finger_stops == ("limit", "limit", "limit")
    assert result.phase == "settle"  # it falls as soon as gravity comes on
    assert "closed on nothing" in result.reason
    assert result.slip > HOLD_TOLERANCE_M


def test_guarded_approach_stops_at_the_true_surface(box, cache):
    # planned on a "predicted" box 1 cm farther away: the true near face is 1 cm closer, so the
    # guarded approach stops 1 cm short of the planned palm pose and still holds the box
    predicted = box.copy()
    predicted.apply_translation([0.01, 0.0, 0.0])
    grasp = autograsp(predicted, side_pose([-0.15, 0.0, 0.0]), spread_deg=0.0)
    assert grasp.palm_pose[0, 3] == pytest.approx(-0.02, abs=1e-4)
    settings = LiftSettings()
    result = lift_test(box, grasp, approach="guarded", shake=False, cache_dir=cache)
    step = settings.approach_speed * settings.time_step
    assert result.travel == pytest.approx(settings.pregrasp_backoff - 0.01, abs=2 * step)
    assert result.success, result.reason
    planned = lift_test(box, grasp, approach="planned", shake=False, lift=0.0, cache_dir=cache)
    assert planned.travel == pytest.approx(settings.pregrasp_backoff)
    with pytest.raises(ValueError, match="approach"):
        lift_test(box, grasp, approach="teleport")


def test_simulated_shapes_match_the_planner_contact(box, good_grasp, cache):
    # the object's padded convex hull and the implicit-cylinder palm reproduce the kinematic
    # model: at autograsp's pose the palm touches the box to within 0.1 mm, without overlap
    with DynamicWorld(box, cache_dir=cache) as world:
        world.place_hand(good_grasp.palm_pose, list(good_grasp.joints_deg))
        world.client.performCollisionDetection()
        points = world.client.getClosestPoints(world.hand_id, world.object_id, 0.005)
        palm = [p[8] for p in points if p[3] == -1]
        assert palm and min(palm) == pytest.approx(0.0, abs=1e-4)
        assert min(p[8] for p in points) > -2e-4
        position, rotation = world.object_in_palm()
        np.testing.assert_allclose(position, [0.0, 0.0, 0.03], atol=2e-5)  # box centre
        assert abs(np.linalg.det(rotation) - 1.0) < 1e-9


def test_mass_properties_of_a_box_match_the_formula(box):
    mass, com, inertia = mass_properties(box, [], density=500.0)
    a, b, c = BOX_EXTENTS
    assert mass == pytest.approx(500.0 * a * b * c)
    np.testing.assert_allclose(com, 0.0, atol=1e-12)
    expected = mass / 12.0 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])
    np.testing.assert_allclose(inertia, expected, rtol=1e-9, atol=1e-15)
    with pytest.raises(ValueError, match="density"):
        mass_properties(box, [], density=0.0)


def l_shape() -> trimesh.Trimesh:
    """Two boxes touching along a face: an L, 10 × 9.5 × 3 cm, not convex."""
    a = trimesh.creation.box(extents=[0.10, 0.03, 0.03])
    b = trimesh.creation.box(extents=[0.03, 0.08, 0.03])
    b.apply_translation([-0.035, 0.055, 0.0])
    return trimesh.util.concatenate([a, b])


def test_concave_mesh_is_decomposed_once_and_cached(tmp_path, monkeypatch):
    shape = l_shape()
    assert not shape.is_convex
    path, pieces = convex_decomposition(shape, cache_dir=tmp_path)
    assert path.parent == tmp_path and path.is_file()
    assert len(pieces) >= 2
    lo, hi = shape.bounds
    for piece in pieces:
        assert np.all(piece >= lo - 2e-3) and np.all(piece <= hi + 2e-3)
    # an open mesh (one face removed) takes its mass from the pieces: close to the L's
    open_mesh = trimesh.Trimesh(shape.vertices, shape.faces[:-1], process=False)
    assert not open_mesh.is_volume
    mass, com, _ = mass_properties(open_mesh, pieces, density=500.0)
    true_mass, true_com, _ = mass_properties(shape, [], density=500.0)
    assert true_mass == pytest.approx(500.0 * (0.10 * 0.03 + 0.03 * 0.08) * 0.03)
    assert mass == pytest.approx(true_mass, rel=0.15)
    np.testing.assert_allclose(com, true_com, atol=5e-3)

    def no_vhacd(*args, **kwargs):
        raise AssertionError("the cached decomposition should have been used")

    monkeypatch.setattr(pybullet, "vhacd", no_vhacd)
    again, pieces_again = convex_decomposition(shape, cache_dir=tmp_path)
    assert again == path
    assert all(np.array_equal(p, q) for p, q in zip(pieces, pieces_again, strict=True))


def test_the_decomposition_cache_keeps_the_most_recently_used(tmp_path, monkeypatch):
    import os

    from grasp.physics import body

    monkeypatch.setenv(body.CACHE_ENTRIES_ENV, "2")  # the settings: its bound and its folder
    monkeypatch.setenv(body.CACHE_DIR_ENV, str(tmp_path))
    boxes = [trimesh.creation.box(extents=[0.05 + 0.01 * k, 0.04, 0.03]) for k in range(3)]
    paths = [convex_decomposition(boxes[k])[0] for k in range(2)]
    for age, path in enumerate(paths):  # the first made 20 s ago, the second 10 s ago
        os.utime(path, (path.stat().st_atime, path.stat().st_mtime - 20 + 10 * age))
    assert convex_decomposition(boxes[0])[0] == paths[0]  # a hit: renewed
    third, _ = convex_decomposition(boxes[2])  # a miss: one entry too many
    assert sorted(tmp_path.glob("*.obj")) == sorted([paths[0], third])  # the unused one went
    monkeypatch.setenv(body.CACHE_ENTRIES_ENV, "0")
    with pytest.raises(ValueError, match="GRASP_CONVEX_CACHE_ENTRIES must be a whole number"):
        convex_decomposition(trimesh.creation.box(extents=[0.09, 0.04, 0.03]))


def test_the_decomposition_cache_stays_under_its_bound_after_1000_meshes(tmp_path, monkeypatch):
    """A long-running service sees a new completion at every view: after 1,000 distinct meshes
    the cache holds its bound's worth, the most recent (boxes: convex, so no V-HACD runs)."""
    from grasp.physics import body

    monkeypatch.setenv(body.CACHE_ENTRIES_ENV, "50")
    last = [convex_decomposition(trimesh.creation.box(extents=[0.05 + 1e-5 * k, 0.04, 0.03]),
                                 cache_dir=tmp_path)[0] for k in range(1000)][-1]
    assert len(list(tmp_path.glob("*.obj"))) == 50 and last.is_file()


def test_bad_inputs_raise_value_errors(box, good_grasp):
    with pytest.raises(ValueError, match="lift"):
        lift_test(box, good_grasp, lift=-0.1)
    with pytest.raises(ValueError, match="GraspResult"):
        lift_test(box, good_grasp.palm_pose)
    with pytest.raises(ValueError, match="friction"):
        lift_test(box, good_grasp, friction=-1.0)
    with pytest.raises(ValueError, match="positive"):
        LiftSettings(time_step=0.0)


def test_command_line_plans_and_lift_tests(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    path = tmp_path / "box.stl"
    trimesh.creation.box(extents=BOX_EXTENTS).export(path)
    # planned on itself, shaken
    code = grasp_main(["lift", str(path), "--candidates", "6", "--top-k", "1"])
    out = capsys.readouterr().out
    assert "planned 1 grasp(s)" in out
    assert "held 1/1" in out
    assert code == 0
    assert any((tmp_path / "cache" / "mvp-grasp" / "convex").glob("*.obj"))


def test_shake_goes_out_and_back_smoothly():
    """The hand's target never jumps: within and between phases it moves at most the peak
    shake or lift speed per step, and its acceleration stays within 2π²f²A (a regression: the
    shake once stayed out and jumped back 3 cm in one step at the next phase)."""
    from grasp.physics.lift import _schedule

    s = LiftSettings()
    directions = np.eye(3)[[0, 1, 2, 0]]
    targets = [np.zeros(3)]
    for _, steps, target in _schedule(0.10, True, directions, s):
        targets += [target((i + 1) * s.time_step) for i in range(steps)]
    targets = np.array(targets)
    speed = np.linalg.norm(np.diff(targets, axis=0), axis=1) / s.time_step
    peak = max(np.pi * s.shake_frequency * s.shake_amplitude, np.pi / 2 * s.lift_speed)
    assert speed.max() <= 1.05 * peak
    accel = np.linalg.norm(np.diff(targets, 2, axis=0), axis=1) / s.time_step**2
    lift_time = 0.10 / s.lift_speed
    lift_peak = (np.pi / lift_time) ** 2 * 0.10 / 2
    assert accel.max() <= 1.05 * max(s.shake_peak_accel, lift_peak)
    np.testing.assert_allclose(targets[-1], [0.0, 0.0, 0.10], atol=1e-9)  # back where it rose to
