"""grasp.planner: candidates around the object, ranked autograsps, deterministic from the seed."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from grasp_scenes import box
from scipy.spatial.transform import Rotation

from grasp.planner import (
    STANDOFF_M,
    candidate_poses,
    plan,
    principal_axes,
    rank_key,
)
from grasp.sim import CollisionScene


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
    return plan(brick, n_candidates=32, seed=0, top_k=None)


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


def test_plan_is_ranked_by_success_epsilon_volume(brick_plan):
    assert len(brick_plan) == 32
    keys = [rank_key(r) for r in brick_plan]
    assert keys == sorted(keys, reverse=True)
    best = brick_plan[0]
    assert best.success and best.epsilon > 0.2 and best.reason == "force closure"
    assert all(r.epsilon <= best.epsilon for r in brick_plan)


def test_plan_is_deterministic_and_top_k_is_a_prefix(brick, brick_plan):
    again = plan(CollisionScene(brick), n_candidates=32, seed=0, top_k=5)
    assert len(again) == 5
    for a, b in zip(again, brick_plan[:5], strict=True):
        assert a.joints_deg == b.joints_deg
        np.testing.assert_array_equal(a.palm_pose, b.palm_pose)
        assert (a.epsilon, a.volume) == (b.epsilon, b.volume)


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
