"""grasp.hand.quality: friction cones, wrenches, the L1 grasp wrench space, epsilon and volume."""

from __future__ import annotations

import numpy as np
import pytest

from grasp.hand.quality import (
    EPSILON_NO_CLOSURE,
    FRICTION_EDGES,
    MU_RUBBER,
    contact_wrenches,
    friction_cone_edges,
    grasp_quality,
    planar_contact_wrenches,
    wrench_space_quality,
)


def test_friction_cone_has_eight_edges_with_unit_normal_part():
    normals = np.array([[0.0, 0.0, 1.0], [1.0, 2.0, 2.0]]) / np.array([[1.0], [3.0]])
    edges = friction_cone_edges(normals, mu=0.5)
    assert edges.shape == (2, FRICTION_EDGES, 3) and FRICTION_EDGES == 8
    # every edge: normal component 1, tangential part of length mu, evenly spaced around
    np.testing.assert_allclose(np.einsum("nkd,nd->nk", edges, normals), 1.0)
    tangents = edges - normals[:, None, :]
    np.testing.assert_allclose(np.linalg.norm(tangents, axis=2), 0.5)
    cos = np.einsum("kd,kd->k", tangents[0], np.roll(tangents[0], 1, axis=0)) / 0.25
    np.testing.assert_allclose(cos, np.cos(2 * np.pi / 8))
    assert MU_RUBBER == 1.0


def test_wrench_torques_are_divided_by_max_radius():
    w = contact_wrenches(
        [[0.1, 0.0, 0.0]], [[-1.0, 0.0, 0.0]], center=np.zeros(3), max_radius=0.1, mu=0.0
    )
    # frictionless: all 8 edges are the normal, torque r × f = 0 (the force passes the centre)
    np.testing.assert_allclose(w, np.tile([-1, 0, 0, 0, 0, 0], (8, 1)), atol=1e-12)
    w = contact_wrenches(
        [[0.0, 0.2, 0.0]], [[-1.0, 0.0, 0.0]], center=np.zeros(3), max_radius=0.1, mu=0.0
    )
    np.testing.assert_allclose(w[0], [-1, 0, 0, 0, 0, 2.0], atol=1e-12)  # (0,.2,0)×(-1,0,0)/.1


@pytest.mark.parametrize("mu", [0.3, 1.0])
def test_two_opposing_planar_contacts_have_force_closure_with_exact_epsilon(mu):
    """Contacts at (±r, 0) on a disc pushing inward: wrenches (∓1, ±μ, ±μ) and (∓1, ∓μ, ∓μ)·.

    The four points form a tetrahedron around the origin; each face is μ / sqrt(μ² + 2) from it
    and its volume is 8μ²/3 (hand-computed).
    """
    r = 0.04
    w = planar_contact_wrenches(
        [[r, 0.0], [-r, 0.0]], [[-1.0, 0.0], [1.0, 0.0]], center=np.zeros(2), max_radius=r, mu=mu
    )
    assert w.shape == (4, 3)
    q = wrench_space_quality(w)
    assert q.force_closure
    assert q.epsilon == pytest.approx(mu / np.sqrt(mu * mu + 2.0), rel=1e-9)
    assert q.volume == pytest.approx(8.0 * mu * mu / 3.0, rel=1e-9)


def test_planar_contacts_without_friction_have_no_closure():
    w = planar_contact_wrenches(
        [[1.0, 0.0], [-1.0, 0.0]],
        [[-1.0, 0.0], [1.0, 0.0]],
        center=np.zeros(2),
        max_radius=1.0,
        mu=0.0,
    )
    q = wrench_space_quality(w)
    assert (q.epsilon, q.volume) == (EPSILON_NO_CLOSURE, 0.0)


def test_single_contact_has_no_force_closure():
    q = grasp_quality([[0.0, 0.0, 0.05]], [[0.0, 0.0, -1.0]], center=np.zeros(3), max_radius=0.05)
    assert (q.epsilon, q.volume) == (EPSILON_NO_CLOSURE, 0.0)
    assert not q.force_closure
    assert (
        grasp_quality(
            np.zeros((0, 3)), np.zeros((0, 3)), center=np.zeros(3), max_radius=1.0
        ).epsilon
        == -1
    )


def test_two_opposing_contacts_on_a_sphere_lack_closure_in_3d():
    """Point contacts cannot resist torque about the line through them: rank-5 wrenches."""
    points = [[0.05, 0.0, 0.0], [-0.05, 0.0, 0.0]]
    normals = [[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]
    w = contact_wrenches(points, normals, center=np.zeros(3), max_radius=0.05)
    assert np.linalg.matrix_rank(w) == 5
    q = grasp_quality(points, normals, center=np.zeros(3), max_radius=0.05)
    assert q.epsilon == EPSILON_NO_CLOSURE and q.volume == 0.0


def test_frictionless_contacts_through_the_centre_cannot_resist_torque():
    """Six frictionless contacts at a cube's face centres: pure forces, no torque: no closure."""
    normals = np.vstack([np.eye(3), -np.eye(3)])
    q = grasp_quality(-0.05 * normals, normals, center=np.zeros(3), max_radius=0.087, mu=0.0)
    assert q.epsilon == EPSILON_NO_CLOSURE


def three_contacts_on_equator(radius=0.05):
    angles = np.radians([90.0, 210.0, 330.0])
    points = radius * np.stack([np.cos(angles), np.sin(angles), np.zeros(3)], axis=1)
    return points, -points / radius


def test_three_frictional_contacts_on_a_sphere_equal_slow_reference():
    """Fast hull epsilon vs the definition ε = min over unit u of max_i w_i·u (sampled).

    Any sampled direction gives an upper bound; with many samples it comes within a few %.
    """
    points, normals = three_contacts_on_equator()
    w = contact_wrenches(points, normals, center=np.zeros(3), max_radius=0.05)
    q = wrench_space_quality(w)
    assert q.force_closure and q.volume > 0.0
    u = np.random.default_rng(0).normal(size=(200_000, 6))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    support = (w @ u.T).max(axis=0)  # (200000,) the support function of the hull
    assert support.min() >= q.epsilon - 1e-9
    assert support.min() <= 1.15 * q.epsilon


def test_force_epsilon_is_the_largest_pure_force_in_the_worst_direction():
    """force_epsilon vs its definition: min over unit forces u of the largest t with t (u, 0)
    in the hull (a linear programme per sampled direction: an upper bound, within a few %)."""
    from scipy.optimize import linprog

    points, normals = three_contacts_on_equator()
    w = contact_wrenches(points, normals, center=np.zeros(3), max_radius=0.05)
    q = wrench_space_quality(w)
    assert q.force_closure
    assert q.force_epsilon >= q.epsilon  # a 6-D ball cut by the force subspace stays inside
    u = np.random.default_rng(1).normal(size=(300, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    reach = []
    for direction in u:  # variables: λ (m) and t; Σλ w = t (u, 0), Σλ = 1, λ >= 0; max t
        target = np.concatenate([direction, np.zeros(3)])
        a_eq = np.vstack([np.c_[w.T, -target], np.r_[np.ones(len(w)), 0.0]])
        b_eq = np.r_[np.zeros(6), 1.0]
        cost = np.r_[np.zeros(len(w)), -1.0]
        bounds = [(0, None)] * len(w) + [(None, None)]
        reach.append(-linprog(cost, A_eq=a_eq, b_eq=b_eq, bounds=bounds).fun)
    assert min(reach) >= q.force_epsilon - 1e-7
    assert min(reach) <= 1.1 * q.force_epsilon
    # without closure there is none
    lone = wrench_space_quality(w[:FRICTION_EDGES])
    assert lone.force_epsilon == EPSILON_NO_CLOSURE


def test_quality_is_invariant_to_object_scale():
    points, normals = three_contacts_on_equator(0.05)
    q1 = grasp_quality(points, normals, center=np.zeros(3), max_radius=0.05)
    q2 = grasp_quality(7.0 * points, normals, center=np.zeros(3), max_radius=0.35)
    assert q2.epsilon == pytest.approx(q1.epsilon, rel=1e-9)
    assert q2.volume == pytest.approx(q1.volume, rel=1e-9)


def test_more_friction_never_hurts():
    points, normals = three_contacts_on_equator()
    eps = [
        grasp_quality(points, normals, center=np.zeros(3), max_radius=0.05, mu=mu).epsilon
        for mu in (0.2, 0.5, 1.0)
    ]
    assert eps[0] < eps[1] < eps[2]


def test_bad_input_raises():
    with pytest.raises(ValueError, match="must match"):
        contact_wrenches(np.zeros((2, 3)), np.ones((3, 3)), center=np.zeros(3), max_radius=1.0)
    with pytest.raises(ValueError, match="max_radius"):
        contact_wrenches(np.zeros((1, 3)), np.ones((1, 3)), center=np.zeros(3), max_radius=0.0)
    with pytest.raises(ValueError, match="non-zero"):
        contact_wrenches(np.zeros((1, 3)), np.zeros((1, 3)), center=np.zeros(3), max_radius=1.0)
    with pytest.raises(ValueError, match="shape"):
        wrench_space_quality(np.zeros(6))
