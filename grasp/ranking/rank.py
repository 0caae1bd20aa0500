"""The ranking of autograsped grasps, best first, and distinct grasps (docs/design.md §7);
:func:`grasp.ranking.select.select` composes them with the verification.

Ranking (:func:`rank`): force closure first, then, on a table, the lift model's probability that
the grasp holds (:mod:`grasp.ranking.lift_model`), then power grasps (the palm touching the
object), then the force epsilon (pure forces through the centre of mass), then the Ferrari–Canny
epsilon of the L1 grasp wrench space; it is chosen to predict the lift test (``grasp.physics``).
The top-k are distinct grasps: a grasp whose palm pose lies within 1 cm and 10° of a better one is
left out (:data:`DISTINCT_M`, :data:`DISTINCT_DEG`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from grasp import defaults
from grasp.hand.autograsp import with_quality
from grasp.hand.collision import CollisionScene
from grasp.hand.result import GraspResult
from grasp.ranking.lift_model import DENSITY_KG_M3, estimated_mass, features, hold_probability

#: Two grasps are the same grasp when their palm poses are closer than both of these.
DISTINCT_M = 0.01
DISTINCT_DEG = 10.0
#: On a table, the hold probability under which a force-closure grasp is refused by default.
HOLD_THRESHOLD = defaults.HOLD_THRESHOLD


def distinct(grasps: Sequence[GraspResult], k: int | None = None) -> list[GraspResult]:
    """The grasps in order, leaving out each one whose palm pose is within :data:`DISTINCT_M`
    and :data:`DISTINCT_DEG` of one already kept; at most ``k``."""
    kept: list[GraspResult] = []
    cos_limit = math.cos(math.radians(DISTINCT_DEG))
    for g in grasps:
        if k is not None and len(kept) >= k:
            break
        same = False
        for other in kept:
            near = np.linalg.norm(g.palm_pose[:3, 3] - other.palm_pose[:3, 3]) < DISTINCT_M
            # rotation angle between the two palm orientations: trace(R1ᵀR2) = 1 + 2 cos θ
            cos = (np.trace(g.palm_pose[:3, :3].T @ other.palm_pose[:3, :3]) - 1.0) / 2.0
            if near and cos > cos_limit:
                same = True
                break
        if not same:
            kept.append(g)
    return kept


def depth_of(result: GraspResult, center: np.ndarray) -> float:
    """Distance (m) from the palm to the object's centre of mass along the approach axis."""
    pose = np.asarray(result.end_palm_pose)
    return float((np.asarray(center) - pose[:3, 3]) @ pose[:3, 2])


def palm_touches(result: GraspResult) -> bool:
    """Whether the palm is one of the grasp's contacts (a power grasp)."""
    return any(c.link == "palm" for c in result.contacts)


def rank_key(result: GraspResult) -> tuple[bool, float, bool, float, float]:
    """Sort key, best first when sorted descending: force closure, on a table the estimated
    probability that the lift holds, the palm touching the object, the force epsilon, then
    epsilon. See :func:`rank`."""
    p = result.hold_probability
    return (result.success, -1.0 if math.isnan(p) else p, palm_touches(result),
            result.force_epsilon, result.epsilon)


def best_distinct(results: Sequence[GraspResult], scene: CollisionScene, top_k: int,
                  min_hold: float = HOLD_THRESHOLD):
    """The first ``top_k`` distinct grasps of the ranking: rank only as many as needed, widened
    while duplicates among them leave fewer than ``top_k`` (the top one is always distinct)."""
    width, memo = top_k, {}  # each grasp is scored once however often the list widens
    while True:
        best = distinct(rank(results, scene, top_k=width, memo=memo, min_hold=min_hold), top_k)
        if len(best) >= top_k or width >= len(results):
            return best
        width = min(2 * width, len(results))


def rank(
    results: Sequence[GraspResult],
    scene: CollisionScene,
    *,
    top_k: int | None = None,
    memo: dict[int, GraspResult] | None = None,
    min_hold: float = HOLD_THRESHOLD,
) -> list[GraspResult]:
    """Score (epsilon, volume) and sort grasps on ``scene``'s object, best first (:func:`rank_key`);
    on a table a force-closure grasp under ``min_hold`` hold probability is a failure.

    What the ranking optimises: a grasp that holds when the object is lifted and carried.
    Force closure comes first (without it some disturbance pulls the object out whatever the
    fingers do). Then power grasps, the palm touching the object: the palm is carried by the
    arm, so the load does not have to pass through the finger motors' 1-1.3 N·m. Then the force
    epsilon (:mod:`grasp.hand.quality`): the largest force through the centre of mass, in the worst
    direction, resisted per unit of contact force; weight and inertia are such forces. Last,
    the Ferrari–Canny epsilon. With 64 candidates on the true mesh, the top grasp by epsilon
    alone held in the lift test for 7 of the 10 named objects, by this ranking for 10 (README).

    On a table (``scene.support_plane``) the second key is the lift model's probability that the
    grasp holds (:mod:`grasp.ranking.lift_model`, learned from lift tests on training-split objects:
    the object's estimated weight against the grip, the grasp's kind, its contacts' heights); every
    grasp is then scored.

    Ties keep the input order. Without a table, with ``top_k`` only the grasps that can still
    enter the top list are scored: force closure (the 6-D hull) is computed in the order of the
    other keys, which need only the contacts and the palm pose, until ``top_k`` force-closure
    grasps were found; the returned list is exactly the first ``top_k`` of the full ranking.
    ``memo`` (id of a result → its scored copy) keeps scores between calls on growing lists of
    the same results.
    """

    def cheap(i: int) -> tuple[bool, bool]:  # the keys that need no wrench hull
        return (bool(results[i].contacts), palm_touches(results[i]))

    scored: dict[int, GraspResult] = {}
    found, last = 0, None
    lazy = top_k is not None and scene.support_plane is None
    for i in sorted(range(len(results)), key=lambda i: (*cheap(i), -i), reverse=True):
        if lazy and found >= top_k and cheap(i) != last:
            break  # ranks below every force-closure grasp found (ties on the cheap keys go on)
        r = results[i]
        if memo is not None and id(r) in memo:
            scored[i] = memo[id(r)]
        else:
            scored[i] = r if not math.isnan(r.epsilon) else with_quality(r, scene)
            if scene.support_plane is not None and scored[i].success:
                scored[i] = _with_hold_probability(scored[i], scene, min_hold)
            if memo is not None:
                memo[id(r)] = scored[i]
        if scored[i].success:
            found, last = found + 1, cheap(i)
    ranked = sorted(scored, key=lambda i: (*rank_key(scored[i]), -i), reverse=True)
    return [scored[i] for i in ranked][: len(results) if top_k is None else top_k]


def _with_hold_probability(result: GraspResult, scene: CollisionScene,
                           min_hold: float = HOLD_THRESHOLD) -> GraspResult:
    """A scored force-closure grasp on a table with the lift model's probability that it holds;
    below ``min_hold`` it is a failure that says so."""
    mass = estimated_mass(scene.mesh)
    p = float(hold_probability(features(result, scene.mesh, scene.support_plane, mass=mass))[0])
    if p >= min_hold or math.isnan(p):
        return dataclasses.replace(result, hold_probability=p)
    reason = (f"force closure, but predicted to drop when lifted (hold probability {p:.2f}; "
              f"{mass:.2f} kg estimated at {DENSITY_KG_M3:g} kg/m³)")
    return dataclasses.replace(result, hold_probability=p, success=False, reason=reason)
