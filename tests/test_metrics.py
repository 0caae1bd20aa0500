"""grasp.evaluate.metrics: Jaccard, F-score@d (Tatarchenko et al. 2019) and the grasp joint
error."""

import numpy as np
import pytest
import trimesh

from completion.grid import GRID_SHAPE
from grasp.evaluate import metrics
from grasp.evaluate.metrics import (
    FScore,
    SurfaceSample,
    fscore,
    fscore_grids,
    grid_side,
    grid_surface_sample,
    jaccard,
    sample_surface,
)

PITCH = 0.005


def _transform(pitch: float = PITCH, shift_x: float = 0.0) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] *= pitch
    t[:3, 3] = [-0.1 + shift_x, -0.1, 0.4]
    return t


def _block(lo, hi) -> np.ndarray:
    g = np.zeros(GRID_SHAPE, dtype=bool)
    g[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = True
    return g


def _points(points) -> SurfaceSample:
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=float)
    return SurfaceSample(p, cKDTree(p))


# ------------------------------------------------------------------------------------- Jaccard


def test_jaccard_of_two_known_grids():
    a = _block((0, 0, 0), (2, 2, 2))  # 8 voxels
    b = _block((1, 0, 0), (3, 2, 2))  # 8 voxels, 4 shared
    assert jaccard(a, b) == pytest.approx(4 / 12)
    assert jaccard(a, a) == 1.0
    assert jaccard(a, _block((5, 5, 5), (6, 6, 6))) == 0.0
    empty = np.zeros(GRID_SHAPE, dtype=bool)
    assert jaccard(empty, empty) == 1.0  # documented: two empty grids agree
    assert jaccard(empty, a) == 0.0


def test_jaccard_checks_its_input():
    with pytest.raises(ValueError, match="40, 40, 40"):
        jaccard(np.zeros((4, 4, 4), bool), np.zeros((4, 4, 4), bool))
    with pytest.raises(ValueError, match="bool"):
        jaccard(np.zeros(GRID_SHAPE), np.zeros(GRID_SHAPE, bool))


# ------------------------------------------------------------------------------------- F-score


def test_fscore_on_hand_computed_points_is_strict():
    pred = _points([[0, 0, 0], [1, 0, 0]])
    truth = _points([[0, 0, 0.5]])
    # d = 0.6: pred point 0 is 0.5 away (in), point 1 is ~1.1 away (out) -> P = 1/2; R = 1.
    (f,) = fscore(pred, truth, [0.6])
    assert (f.precision, f.recall) == (0.5, 1.0)
    assert f.fscore == pytest.approx(2 * 0.5 * 1 / 1.5)
    # d = 0.5 exactly: the strict "<" counts nothing.
    (f,) = fscore(pred, truth, [0.5])
    assert f == FScore(0.5, 0.0, 0.0, 0.0)


def test_fscore_empty_cases_and_bad_thresholds():
    empty, some = SurfaceSample.empty(), _points([[0, 0, 0]])
    assert fscore(empty, some, [0.1])[0].fscore == 0.0
    assert fscore(some, empty, [0.1])[0].fscore == 0.0
    assert fscore(empty, empty, [0.1])[0].fscore == 1.0
    with pytest.raises(ValueError, match="positive"):
        fscore(some, some, [0.0])


def test_fscore_of_a_mesh_with_itself_is_one():
    cube = _block((10, 10, 8), (30, 30, 28))
    t = _transform()
    truth = grid_surface_sample(cube, t, threshold=0.5, seed=3)
    f1, f2 = fscore_grids(cube, truth, t, threshold=0.5, seed=3)
    assert f1.fscore == 1.0 and f2.fscore == 1.0
    assert f1.d == pytest.approx(0.01 * 40 * PITCH)
    assert f2.d == pytest.approx(0.02 * 40 * PITCH)


@pytest.mark.parametrize("shape", ["cube", "ball", "slab"])
def test_independent_samples_of_one_surface_score_at_least_098(shape):
    """The sampling is dense enough that F@1% measures the surfaces, not the sampling."""
    idx = np.indices(GRID_SHAPE).transpose(1, 2, 3, 0)
    grids = {
        "cube": _block((4, 4, 4), (36, 36, 36)),  # the largest surface a fitted grid holds
        "ball": np.linalg.norm(idx - 19.5, axis=-1) < 15,
        "slab": _block((2, 15, 2), (38, 25, 38)),
    }
    t = _transform()
    truth = grid_surface_sample(grids[shape], t, threshold=0.5, seed=1)
    f1, f2 = fscore_grids(grids[shape], truth, t, threshold=0.5, seed=2)
    assert f1.fscore >= 0.98 and f2.fscore >= 0.999


def test_truth_sample_keeps_the_part_inside_the_grid():
    t = _transform()  # grid from (-0.1, -0.1, 0.4) to (0.1, 0.1, 0.6), 5 mm voxels
    inside = trimesh.creation.box((0.05, 0.05, 0.05))
    inside.apply_translation([0.0, 0.0, 0.5])
    half_out = trimesh.creation.box((0.1, 0.05, 0.05))
    half_out.apply_translation([0.1, 0.0, 0.5])  # x from 0.05 to 0.15: half outside
    sample = metrics.truth_surface_sample([inside, half_out], t, seed=0)
    assert sample.points[:, 0].max() <= 0.1 + PITCH / 2
    assert sample.points[:, 0].min() < -0.02  # the inside box is there
    assert len(sample.points) >= metrics.FSCORE_SAMPLES // 2


def test_fscore_of_a_shifted_mesh():
    """Shifted by 1.5% of the grid side: F@1% well below 1, F@2% (d > shift) all but 1.

    (At a shift of exactly 2% the faces across the shift sit at distance d, which the strict
    ``<`` rejects; 1.5% keeps the test away from that edge.)
    """
    cube = _block((10, 10, 8), (30, 30, 28))
    t = _transform()
    side = grid_side(t)
    assert side == pytest.approx(40 * PITCH)
    truth = grid_surface_sample(cube, t, threshold=0.5, seed=3)
    moved = _transform(shift_x=0.015 * side)
    f1, f2 = fscore_grids(cube, truth, moved, threshold=0.5, seed=4)
    assert f1.fscore < 0.8
    assert f2.fscore > 0.98


def test_fscore_of_an_empty_prediction_is_zero():
    cube = _block((10, 10, 8), (30, 30, 28))
    empty = np.zeros(GRID_SHAPE, dtype=np.float32)
    truth = grid_surface_sample(cube, _transform(), threshold=0.5, seed=3)
    f1, f2 = fscore_grids(empty, truth, _transform(), threshold=0.5)
    assert f1.fscore == 0.0 and f2.fscore == 0.0


def test_surface_samples_are_seeded():
    box = trimesh.creation.box((0.1, 0.05, 0.08))
    a = sample_surface(box, count=100, seed=1).points
    b = sample_surface(box, count=100, seed=1).points
    c = sample_surface(box, count=100, seed=2).points
    assert a.shape == (100, 3)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert sample_surface(None).is_empty


# ------------------------------------------------------------------------------------- grasp


def _needs_planner():
    pytest.importorskip("grasp.hand.autograsp", reason="grasp.hand.autograsp is not written yet")
    pytest.importorskip("grasp.planner", reason="grasp.planner is not written yet")


def _object() -> trimesh.Trimesh:
    """A 6 × 4 × 9 cm box 30 cm in front of a camera (camera frame, metres)."""
    mesh = trimesh.creation.box((0.06, 0.04, 0.09))
    mesh.apply_translation([0.0, 0.0, 0.3])
    return mesh


def test_joint_error_of_a_mesh_with_itself_is_zero():
    _needs_planner()
    mesh = _object()
    result = metrics.grasp_joint_error(mesh, mesh.copy(), n_candidates=4, seed=0)
    assert result.error_deg == 0.0, result.reason
    np.testing.assert_array_equal(result.per_joint_deg, np.zeros(8))
    assert result.planned.palm_pose.shape == (4, 4)
    np.testing.assert_array_equal(result.on_prediction.joints_deg, result.on_truth.joints_deg)
    summary = result.as_dict()
    assert summary["error_deg"] == 0.0 and len(summary["on_truth"]["joints_deg"]) == 8


def test_joint_error_against_a_scaled_copy_is_small_and_positive():
    _needs_planner()
    mesh = _object()
    errors = []
    for scale in (1.02, 1.08):
        truth = mesh.copy()
        truth.apply_scale(scale)
        truth.apply_translation(mesh.centroid - truth.centroid)
        result = metrics.grasp_joint_error(mesh, truth, n_candidates=4, seed=0)
        assert result.error_deg is not None, result.reason
        assert result.per_joint_deg.shape == (8,)
        assert result.error_deg == pytest.approx(result.per_joint_deg.mean())
        spreads = [metrics.JOINT_NAMES.index(n) for n in ("f1_spread", "f2_spread")]
        assert (result.per_joint_deg[spreads] == 0).all()  # the spread is never moved
        errors.append(result.error_deg)
    # a larger object stops the fingers earlier: a small error that grows with the difference
    assert 0.0 < errors[0] < errors[1] < 5.0


def test_joint_error_without_a_prediction_surface_is_a_value():
    result = metrics.grasp_joint_error(None, _object(), n_candidates=1)
    assert result.error_deg is None and "empty" in result.reason
    assert result.as_dict()["error_deg"] is None


def test_joint_error_over_the_moving_joints_leaves_the_spreads_out():
    per_joint = np.array([0.0, 2.0, 4.0, 0.0, 6.0, 8.0, 10.0, 12.0])  # spreads at 0 and 3
    error = metrics.JointError(float(per_joint.mean()), per_joint)
    assert metrics.MOVING_JOINTS == ("f1_prox", "f1_dist", "f2_prox", "f2_dist", "f3_prox",
                                     "f3_dist")
    assert error.error_moving_deg == pytest.approx(7.0)
    assert error.as_dict()["error_moving_deg"] == pytest.approx(7.0)
    assert metrics.JointError(None, reason="no grasp").error_moving_deg is None
