"""Grasp quality: contact wrenches, the L1 grasp wrench space, Ferrari–Canny epsilon and volume.

Each contact contributes the edges of its linearised friction cone (``FRICTION_EDGES`` = 8 for a
point contact with friction): unit normal force plus μ times a unit tangent, so every edge has a
normal component of exactly 1. Torques are taken about the object's centre and divided by its
maximum radius (largest centre-to-vertex distance), which makes force and torque commensurate and
the measures independent of the object's scale. The L1 grasp wrench space is the convex hull of
all contacts' edge wrenches (GraspIt!'s "L1 norm" GWS; Ferrari & Canny 1992).

- ``epsilon``: radius of the largest ball around the origin inside the hull (the distance from the
  origin to the nearest facet). Without force closure (origin outside the hull, on its boundary,
  or a hull of lower dimension than the wrench space) it is ``EPSILON_NO_CLOSURE`` = −1, as in
  GraspIt!.
- ``volume``: the hull's volume (0 when the hull is degenerate).
- ``force_epsilon``: the same radius in the subspace of pure forces through the centre (zero
  torque): the largest force, in the worst direction, that the grasp resists per unit of total
  normal force. A carried object's weight and its inertia under the hand's acceleration are
  such forces (the centre is the centre of mass), so this is the measure of holding it while
  lifting and shaking (a task wrench space in the sense of Borst et al. 2004). −1 without
  closure.

Friction: μ = ``MU_RUBBER`` = 1.0. The BH8-280 model in GraspIt! has rubber-coated links and
hands/barrett/README.md quotes μ = 1.0 for rubber on most materials; the objects here carry no
material, so the rubber value is the one that describes the hand. Pass ``mu`` to use another.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

#: Coulomb friction of the hand's rubber-coated links on most materials (hands/barrett/README).
MU_RUBBER = 1.0
#: Edges of the linearised friction cone of one point contact.
FRICTION_EDGES = 8
#: Epsilon reported when the grasp has no force closure.
EPSILON_NO_CLOSURE = -1.0
#: The origin counts as inside the hull only if every facet is at least this far from it.
_CLOSURE_TOL = 1e-9
#: Force components at the front of a wrench: (fx, fy, fz, τ…) in 3-D, (fx, fy, τ) planar.
_FORCE_DIMS = {6: 3, 3: 2}


@dataclass(frozen=True)
class GraspQuality:
    """Ferrari–Canny epsilon, volume and force epsilon of a grasp wrench space."""

    epsilon: float
    volume: float
    force_epsilon: float = EPSILON_NO_CLOSURE

    @property
    def force_closure(self) -> bool:
        return self.epsilon > 0.0


def _tangent_basis(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (n, 3) each, orthogonal to the unit (n, 3) ``normals``."""
    helper = np.zeros_like(normals)
    helper[np.arange(len(normals)), np.argmin(np.abs(normals), axis=1)] = 1.0
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    return t1, t2


def _check_contacts(points: np.ndarray, normals: np.ndarray, dim: int, max_radius: float):
    points = np.asarray(points, dtype=np.float64).reshape(-1, dim)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, dim)
    if points.shape != normals.shape:
        raise ValueError(f"points {points.shape} and normals {normals.shape} must match")
    if not max_radius > 0.0:
        raise ValueError(f"max_radius must be positive, got {max_radius}")
    norms = np.linalg.norm(normals, axis=1, keepdims=True)
    if np.any(norms < 1e-12):
        raise ValueError("contact normals must be non-zero")
    return points, normals / norms


def friction_cone_edges(
    normals: np.ndarray, *, mu: float = MU_RUBBER, n_edges: int = FRICTION_EDGES
) -> np.ndarray:
    """Edges of the linearised friction cones.

    Parameters
    ----------
    normals : (n, 3) float
        Unit contact normals pointing into the object.

    Returns
    -------
    (n, n_edges, 3) float: n + μ (cos φ_k t1 + sin φ_k t2), φ_k = 2πk / n_edges.
    """
    if mu < 0.0 or n_edges < 1:
        raise ValueError(f"need mu >= 0 and n_edges >= 1, got mu={mu}, n_edges={n_edges}")
    t1, t2 = _tangent_basis(normals)
    phi = 2.0 * np.pi * np.arange(n_edges) / n_edges
    tangents = np.cos(phi)[None, :, None] * t1[:, None] + np.sin(phi)[None, :, None] * t2[:, None]
    return normals[:, None, :] + mu * tangents


def contact_wrenches(
    points: np.ndarray,
    normals: np.ndarray,
    *,
    center: np.ndarray,
    max_radius: float,
    mu: float = MU_RUBBER,
    n_edges: int = FRICTION_EDGES,
) -> np.ndarray:
    """Wrenches of the friction-cone edges of 3-D point contacts.

    Parameters
    ----------
    points : (n, 3) float
        Contact points (metres).
    normals : (n, 3) float
        Contact normals pointing into the object (normalised here).
    center : (3,) float
        Torque reference point (the object's centre).
    max_radius : float
        The object's maximum radius; torques are divided by it.

    Returns
    -------
    (n * n_edges, 6) float: rows (force, torque / max_radius).
    """
    points, normals = _check_contacts(points, normals, 3, max_radius)
    forces = friction_cone_edges(normals, mu=mu, n_edges=n_edges)  # (n, k, 3)
    arms = (points - np.asarray(center, dtype=np.float64))[:, None, :] / max_radius
    torques = np.cross(np.broadcast_to(arms, forces.shape), forces)
    return np.concatenate([forces, torques], axis=2).reshape(-1, 6)


def planar_contact_wrenches(
    points: np.ndarray,
    normals: np.ndarray,
    *,
    center: np.ndarray,
    max_radius: float,
    mu: float = MU_RUBBER,
) -> np.ndarray:
    """Wrenches (fx, fy, τz / max_radius) of planar point contacts: two cone edges n ± μ t.

    Parameters
    ----------
    points, normals : (n, 2) float
        Contact points and inward normals in the plane.
    center : (2,) float
        Torque reference point.

    Returns
    -------
    (2 n, 3) float.
    """
    points, normals = _check_contacts(points, normals, 2, max_radius)
    tangents = np.stack([-normals[:, 1], normals[:, 0]], axis=1)
    forces = np.stack([normals + mu * tangents, normals - mu * tangents], axis=1)  # (n, 2, 2)
    arms = (points - np.asarray(center, dtype=np.float64))[:, None, :] / max_radius
    torques = arms[..., 0] * forces[..., 1] - arms[..., 1] * forces[..., 0]
    return np.concatenate([forces, torques[..., None]], axis=2).reshape(-1, 3)


def wrench_space_quality(wrenches: np.ndarray) -> GraspQuality:
    """Epsilon and volume of the convex hull of (m, d) ``wrenches`` (d = 6, or 3 for planar)."""
    wrenches = np.asarray(wrenches, dtype=np.float64)
    if wrenches.ndim != 2 or wrenches.shape[1] < 2:
        raise ValueError(f"wrenches must have shape (m, d) with d >= 2, got {wrenches.shape}")
    dim = wrenches.shape[1]
    if len(wrenches) <= dim or np.linalg.matrix_rank(wrenches - wrenches.mean(0), 1e-9) < dim:
        return GraspQuality(EPSILON_NO_CLOSURE, 0.0)  # flat hull: no volume, no closure
    try:
        # joggled input (QJ): simplicial facets, no precision merges; 2-3x faster in 6-D and
        # robust to the near-duplicate wrenches of neighbouring contacts (perturbation ~1e-11)
        hull = ConvexHull(wrenches, qhull_options="QJ")
    except QhullError:
        return GraspQuality(EPSILON_NO_CLOSURE, 0.0)
    # facets: normal · x + offset <= 0 inside, unit normals, so -offset = distance to the origin
    distances = -hull.equations[:, -1]
    nearest = float(distances.min())
    if nearest <= _CLOSURE_TOL:
        return GraspQuality(EPSILON_NO_CLOSURE, float(hull.volume))
    # the hull cut by the force subspace (zero torque) is {f : n_F·f <= distance} per facet; the
    # largest ball in it has radius min distance / |n_F| (facets parallel to it do not bound it)
    n_force = np.linalg.norm(hull.equations[:, : _FORCE_DIMS[dim]], axis=1)
    bounded = n_force > 1e-12
    force = float((distances[bounded] / n_force[bounded]).min()) if bounded.any() else nearest
    return GraspQuality(nearest, float(hull.volume), force)


def grasp_quality(
    points: np.ndarray,
    normals: np.ndarray,
    *,
    center: np.ndarray,
    max_radius: float,
    mu: float = MU_RUBBER,
    n_edges: int = FRICTION_EDGES,
) -> GraspQuality:
    """Epsilon and volume of 3-D point contacts ((n, 3) points and inward normals)."""
    if len(np.asarray(points).reshape(-1, 3)) == 0:
        return GraspQuality(EPSILON_NO_CLOSURE, 0.0)
    wrenches = contact_wrenches(
        points, normals, center=center, max_radius=max_radius, mu=mu, n_edges=n_edges
    )
    return wrench_space_quality(wrenches)


def contacts_wrenches(
    contacts: Sequence, *, center: np.ndarray, max_radius: float, mu: float = MU_RUBBER
) -> np.ndarray:
    """(8 n, 6) :func:`contact_wrenches` of records with ``.point`` and ``.normal``."""
    if not contacts:
        return np.zeros((0, 6))
    points = np.array([c.point for c in contacts])
    normals = np.array([c.normal for c in contacts])
    return contact_wrenches(points, normals, center=center, max_radius=max_radius, mu=mu)


def contacts_quality(
    contacts: Sequence, *, center: np.ndarray, max_radius: float, mu: float = MU_RUBBER
) -> GraspQuality:
    """:func:`grasp_quality` of records with ``.point`` and ``.normal``
    (``grasp.hand.collision.Contact``)."""
    if not contacts:
        return GraspQuality(EPSILON_NO_CLOSURE, 0.0)
    return wrench_space_quality(
        contacts_wrenches(contacts, center=center, max_radius=max_radius, mu=mu)
    )
