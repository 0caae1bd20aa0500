"""Grasp planning: candidate palm poses around an object, autograsp each, rank by quality.

Candidates (deterministic from ``seed``):

1. Along the object's principal axes (±3 directions), with the fingers' opposition axis (palm y)
   laid along each of the two other principal axes, spreads 0° and 60° (24 poses). Boxes,
   cylinders and most man-made objects are grasped best this way.
2. The rest from a Fibonacci sphere of approach directions, randomly rotated by the seed, each
   with a seeded roll about the approach axis and a spread drawn from ``spreads_deg``.

Every candidate aims the palm's +z at the object's centre from outside its bounding sphere and
approaches until contact. Results come back as values: a candidate that fails is a
``GraspResult`` with ``success=False`` and its reason, ranked after the successes.

Ranking (:func:`rank`): force closure first, then power grasps (the palm touching the object),
then the force epsilon (pure forces through the centre of mass), then the Ferrari–Canny epsilon
of the L1 grasp wrench space; it is chosen to predict the lift test (``grasp.physics``). The top-k
are distinct grasps: a grasp whose palm pose lies within 1 cm and 10° of a better one is left
out (:data:`DISTINCT_M`, :data:`DISTINCT_DEG`).

Speed: a distance-field screen (:mod:`grasp.screen`) predicts the approach of every candidate
at once, and only the most promising (:data:`EXACT_CANDIDATES` a round) get the exact fcl
autograsp; ``exact=None`` autograsps all of them.

A support plane (``support_plane=SupportPlane(...)``, n·x + d = 0 in the mesh's frame, n up, the
object on its upper side) is the table, an obstacle to the hand as in GraspIt!
(:mod:`grasp.autograsp`): no link goes below it. Its candidates (:func:`table_candidates`) start
with top-down and, for a low object, fingertip grasps; none approaches from below.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh

from completion.grid import transform_points
from grasp.autograsp import GraspResult, autograsp, with_quality
from grasp.screen import Screen, finger_reach, open_hand_lowest
from grasp.sim import CollisionScene, SupportPlane, check_mesh, fibonacci_directions
from hands.barrett import JOINT_NAMES, HandKinematics

#: Spreads (degrees) the random candidates draw from: parallel fingers, tripod, T, and between.
DEFAULT_SPREADS_DEG: tuple[float, ...] = (0.0, 30.0, 60.0, 90.0)
#: The palm starts this far outside the object's bounding sphere (metres).
STANDOFF_M = 0.02
#: Largest object the planner tries, as its bounding-box diagonal (metres). The open BH8-282
#: spans about 0.3 m, so bigger shapes come back as failures (no force closure); one several
#: metres across is refused outright: approaching it in 10 mm steps would take minutes.
MAX_OBJECT_DIAGONAL_M = 2.0
#: Two grasps are the same grasp when their palm poses are closer than both of these.
DISTINCT_M = 0.01
DISTINCT_DEG = 10.0
#: Candidates the planner autograsps exactly per round, the screen's most promising first.
EXACT_CANDIDATES = 4
#: Spacing of the hand's points in the planner's screen (metres): 430 points on the hand.
SCREEN_SPACING_M = 0.02
#: A grasp whose hand reaches further below the table is dropped (only rounding can put it there).
TABLE_TOL_M = 1e-6
#: Open hands start at least this far above the table (metres).
TABLE_CLEARANCE_M = 0.002
#: Fingertip grasps stop the palm this far above the closing fingers' deepest reach (metres), so
#: that the tips sweep just over the table.
PINCH_CLEARANCE_M = 0.004

_KINEMATICS = HandKinematics()


def _link_poses(grasp: GraspResult) -> dict[str, np.ndarray]:
    """Every link's (4, 4) link→world pose in ``grasp``, by the hand's kinematics."""
    joints = np.radians(np.asarray(grasp.joints_deg, dtype=np.float64))
    return {link: grasp.palm_pose @ pose for link, pose in _KINEMATICS.link_poses(joints).items()}


def hand_primitives(grasp: GraspResult) -> list[tuple[str, str, tuple[float, ...], np.ndarray]]:
    """The hand of ``grasp`` as collision primitives placed by the hand's kinematics:
    (link, "box" or "cylinder", size, (4, 4) primitive→world pose) each. Box sizes are full
    extents; a cylinder is (radius, length) along its local z."""
    links = _link_poses(grasp)
    return [
        (prim.link, prim.kind, tuple(prim.size), links[prim.link] @ prim.pose)
        for prim in _KINEMATICS.primitives
    ]


def hand_points(grasp: GraspResult) -> np.ndarray:
    """(n, 3) points on the hand's collision primitives in ``grasp`` (world): every box's
    corners and 64 points around each rim of every cylinder."""
    angles = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
    out = []
    for _, kind, size, pose in hand_primitives(grasp):
        if kind == "box":
            local = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
            local = 0.5 * local * np.asarray(size)
        else:
            rim = np.c_[size[0] * np.cos(angles), size[0] * np.sin(angles), np.zeros(64)]
            local = np.concatenate([rim + [0.0, 0.0, z] for z in (-size[1] / 2, size[1] / 2)])
        out.append(transform_points(local, pose))
    return np.concatenate(out)


def hand_clearance(plane: SupportPlane, grasp: GraspResult) -> float:
    """Height (m) of the hand's lowest point above ``plane`` in ``grasp`` (negative: below)."""
    return float(
        min(plane.lowest(kind, size, pose) for _, kind, size, pose in hand_primitives(grasp))
    )


def crosses(plane: SupportPlane, grasp: GraspResult, *, tol: float = TABLE_TOL_M) -> bool:
    """Whether any part of the hand reaches more than ``tol`` below the support plane."""
    return hand_clearance(plane, grasp) < -tol


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


@dataclass(frozen=True)
class Candidate:
    """One pre-grasp: palm→world (4, 4) pose aimed at the object, and a spread in degrees."""

    palm_pose: np.ndarray
    spread_deg: float
    source: str  # "principal", "sphere", or with a support plane "top" or "pinch"
    travel: float | None = None  # longest approach (metres); None: the planner's


def principal_axes(mesh: trimesh.Trimesh) -> np.ndarray:
    """(3, 3) rows: the object's principal axes, longest extent first (area-weighted PCA).

    Signs are fixed (largest component positive) so that the axes are deterministic.
    """
    weights = mesh.area_faces / max(mesh.area, 1e-300)
    centroids = mesh.triangles_center
    mean = weights @ centroids
    centred = (centroids - mean) * np.sqrt(weights)[:, None]
    # full_matrices only for 1-2 faces (3 axes); for many faces it would build a faces² matrix
    _, _, axes = np.linalg.svd(centred, full_matrices=len(centred) < 3)
    axes = axes[:3]
    flip = np.sign(axes[np.arange(3), np.argmax(np.abs(axes), axis=1)])
    axes = axes * flip[:, None]
    if np.linalg.det(axes) < 0:
        axes[2] *= -1.0
    return axes


def _palm_pose(approach: np.ndarray, opposition: np.ndarray, target: np.ndarray, distance: float):
    """Palm pose with +z along ``approach``, +y near ``opposition``, ``distance`` before target."""
    z = approach / np.linalg.norm(approach)
    y = opposition - np.dot(opposition, z) * z
    if np.linalg.norm(y) < 1e-9:
        y = np.cross(z, np.eye(3)[int(np.argmin(np.abs(z)))])
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = x, y, z
    pose[:3, 3] = target - distance * z
    return pose


def candidate_poses(
    mesh: trimesh.Trimesh,
    *,
    n_candidates: int = 64,
    seed: int | np.random.Generator = 0,
    spreads_deg: Sequence[float] = DEFAULT_SPREADS_DEG,
    standoff: float = STANDOFF_M,
) -> list[Candidate]:
    """``n_candidates`` pre-grasp poses around ``mesh`` (principal-axis ones first)."""
    check_mesh(mesh)
    if n_candidates < 1:
        raise ValueError(f"n_candidates must be >= 1, got {n_candidates}")
    if not spreads_deg or any(not 0.0 <= s <= 180.0 for s in spreads_deg):
        raise ValueError(f"spreads_deg must be non-empty values in [0, 180], got {spreads_deg}")
    rng = np.random.default_rng(seed)
    center = np.asarray(mesh.bounds.mean(axis=0))
    distance = float(np.linalg.norm(mesh.vertices - center, axis=1).max()) + standoff
    axes = principal_axes(mesh)
    out: list[Candidate] = []
    for i in range(3):
        for sign in (1.0, -1.0):
            for j in (k for k in range(3) if k != i):
                for spread in (0.0, 60.0):
                    pose = _palm_pose(sign * axes[i], axes[j], center, distance)
                    out.append(Candidate(pose, spread, "principal"))
    n_sphere = max(n_candidates - len(out), 0)
    out = out[:n_candidates]
    if n_sphere:
        rotation = _random_rotation(rng)
        directions = fibonacci_directions(n_sphere) @ rotation.T
        rolls = rng.uniform(0.0, 2.0 * math.pi, n_sphere)
        spreads = rng.choice(np.asarray(spreads_deg, dtype=np.float64), n_sphere)
        for direction, roll, spread in zip(directions, rolls, spreads, strict=True):
            approach = -direction  # from the sphere point toward the centre
            base = _palm_pose(approach, np.eye(3)[int(np.argmin(np.abs(approach)))], center, 0.0)
            opposition = math.cos(roll) * base[:3, 1] + math.sin(roll) * base[:3, 0]
            pose = _palm_pose(approach, opposition, center, distance)
            out.append(Candidate(pose, float(spread), "sphere"))
    return out


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """(3, 3) uniformly random rotation (unit quaternion from four normals)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def table_candidates(
    mesh: trimesh.Trimesh,
    plane: SupportPlane,
    *,
    n_candidates: int = 64,
    seed: int | np.random.Generator = 0,
    spreads_deg: Sequence[float] = DEFAULT_SPREADS_DEG,
    standoff: float = STANDOFF_M,
    travel: float = 0.2,
) -> list[Candidate]:
    """``n_candidates`` pre-grasp poses around ``mesh`` resting on ``plane``: top-down ones
    (palm +z against the normal, fingers across each axis of the footprint, spreads 0° and 60°);
    for an object lower than the fingers' reach, fingertip ones (the same, the approach ending
    where the closing tips sweep just over the table); then :func:`candidate_poses`'s that do
    not approach from below. Every open hand starts clear of the table (:func:`_clear_of_table`;
    ``travel``: the others' approach, metres)."""
    check_mesh(mesh)
    if n_candidates < 1:
        raise ValueError(f"n_candidates must be >= 1, got {n_candidates}")
    center = np.asarray(mesh.bounds.mean(axis=0))
    distance = float(np.linalg.norm(mesh.vertices - center, axis=1).max()) + standoff
    axes = _footprint_axes(mesh, plane)[::-1]  # across the narrow side first
    tops = [(_palm_pose(-plane.normal, a, center, distance), s) for a in axes for s in (0.0, 60.0)]
    out = [Candidate(pose, spread, "top") for pose, spread in tops]
    pinch = finger_reach() + PINCH_CLEARANCE_M  # palm face height of a fingertip grasp
    if plane.height(mesh.vertices).max() < pinch:
        for pose, spread in tops:
            above, start = float(plane.height(pose[:3, 3])), pose.copy()
            start[:3, 3] += max(pinch - above, 0.0) * plane.normal
            out.append(Candidate(start, spread, "pinch", max(above - pinch, 0.0)))
    pool = candidate_poses(mesh, n_candidates=2 * n_candidates + 24, seed=seed,
                           spreads_deg=spreads_deg, standoff=standoff)
    out += [c for c in pool if c.palm_pose[:3, 2] @ plane.normal <= 1e-9]
    unique: dict[tuple, Candidate] = {}  # a top-down candidate may also be a principal one
    for c in out:
        unique.setdefault((c.spread_deg, (np.round(c.palm_pose, 9) + 0.0).tobytes()), c)
    return _clear_of_table(list(unique.values())[:n_candidates], plane, travel)


def _footprint_axes(mesh: trimesh.Trimesh, plane: SupportPlane) -> np.ndarray:
    """(2, 3) unit vectors in ``plane``: the object's footprint's long axis, then the short one
    (area-weighted PCA of the faces projected on the plane; largest component positive)."""
    n = plane.normal
    e1 = _palm_pose(n, np.zeros(3), np.zeros(3), 0.0)[:3, 0]  # any unit vector in the plane
    basis = np.stack([e1, np.cross(n, e1)])  # (2, 3)
    weights = mesh.area_faces / max(mesh.area, 1e-300)
    centroids = mesh.triangles_center
    flat = (centroids - weights @ centroids) @ basis.T  # (f, 2)
    _, vectors = np.linalg.eigh((flat * weights[:, None]).T @ flat)
    long = vectors[:, 1] @ basis
    long *= np.sign(long[np.argmax(np.abs(long))])
    return np.stack([long, np.cross(n, long)])


def _clear_of_table(
    candidates: Sequence[Candidate], plane: SupportPlane, travel: float
) -> list[Candidate]:
    """The candidates, each open hand less than :data:`TABLE_CLEARANCE_M` above ``plane`` moved
    back along its approach (if it descends at least 30°) or up the normal."""
    palms = np.stack([c.palm_pose for c in candidates])
    lowest = open_hand_lowest(plane, palms, np.array([c.spread_deg for c in candidates]))
    out = []
    for c, low in zip(candidates, lowest, strict=True):
        need = TABLE_CLEARANCE_M - float(low)
        pose, limit = c.palm_pose.copy(), travel if c.travel is None else c.travel
        descent = -float(pose[:3, 2] @ plane.normal)
        if need <= 0.0:
            out.append(c)
        elif descent >= 0.5:  # keep the approach line: start further back
            pose[:3, 3] -= need / descent * pose[:3, 2]
            out.append(dataclasses.replace(c, palm_pose=pose, travel=limit + need / descent))
        else:
            pose[:3, 3] += need * plane.normal
            out.append(dataclasses.replace(c, palm_pose=pose, travel=limit))
    return out


def too_large(mesh: trimesh.Trimesh) -> str | None:
    """Why the hand cannot grasp ``mesh`` at all (None when it may)."""
    diagonal = float(np.linalg.norm(mesh.extents))
    if diagonal <= MAX_OBJECT_DIAGONAL_M:
        return None
    return (
        f"the shape is {diagonal:.3g} m across (bounding-box diagonal), far beyond the "
        f"BarrettHand's reach; the planner tries shapes up to {MAX_OBJECT_DIAGONAL_M:g} m"
    )


def depth_of(result: GraspResult, center: np.ndarray) -> float:
    """Distance (m) from the palm to the object's centre of mass along the approach axis."""
    pose = np.asarray(result.palm_pose)
    return float((np.asarray(center) - pose[:3, 3]) @ pose[:3, 2])


def palm_touches(result: GraspResult) -> bool:
    """Whether the palm is one of the grasp's contacts (a power grasp)."""
    return any(c.link == "palm" for c in result.contacts)


def rank_key(result: GraspResult) -> tuple[bool, bool, float, float]:
    """Sort key, best first when sorted descending: force closure, the palm touching the object,
    the force epsilon, then epsilon. See :func:`rank`."""
    return (result.success, palm_touches(result), result.force_epsilon, result.epsilon)


def plan(
    mesh: trimesh.Trimesh | CollisionScene,
    *,
    n_candidates: int = 64,
    seed: int = 0,
    top_k: int | None = 10,
    spreads_deg: Sequence[float] = DEFAULT_SPREADS_DEG,
    max_travel: float | None = None,
    support_plane: SupportPlane | None = None,
    exact: int | None = EXACT_CANDIDATES,
    timings: dict[str, float] | None = None,
) -> list[GraspResult]:
    """Plan BarrettHand grasps on ``mesh``: the best ``top_k`` distinct grasps of
    ``n_candidates`` candidates.

    Stages: the candidates (:func:`candidate_poses`, :func:`table_candidates`); a screen that
    predicts, for every candidate at once, where its approach stops and whether the palm is
    what touches (:meth:`grasp.screen.Screen.predict`, a distance field of the mesh); the exact
    autograsp (approach, close, contacts) of the most promising ``exact`` candidates by that
    prediction, then of the next ``exact`` while fewer than ``top_k`` distinct force-closure
    grasps were found; the ranking (:func:`rank`) of those.

    Parameters
    ----------
    mesh : trimesh.Trimesh or CollisionScene
        The object, world frame, metres.
    n_candidates : int
        Number of candidate pre-grasps (see :func:`candidate_poses`).
    seed : int
        Seed of the random candidates; the same seed gives the same plan.
    top_k : int or None
        How many distinct grasps to return, best first (None: every candidate's result,
        ranked, near-duplicates included; every candidate is then autograsped).
    spreads_deg : sequence of float
        Spreads the random candidates choose from.
    max_travel : float or None
        Longest approach; default: through the whole bounding sphere.
    support_plane : SupportPlane or None
        The table, in the mesh's frame (default: the scene's): an obstacle to the hand; the
        candidates are then :func:`table_candidates` (none from below).
    exact : int or None
        Candidates autograsped exactly per round, most promising first (None: all of them, no
        screen: the complete ranking, for diagnostics).
    timings : dict or None
        Filled with each stage's seconds ("setup": the collision model and the candidates;
        "screen"; "autograsp"; "rank", with the quality measures) and the counts
        "screened" and "autograsped".

    Returns
    -------
    list of GraspResult, sorted by :func:`rank_key` descending, ties in candidate order; with
    ``top_k``, without near-duplicates (:func:`distinct`).
    """
    clock = time.perf_counter()
    stages = {"setup": 0.0, "screen": 0.0, "autograsp": 0.0, "rank": 0.0}

    def lap(stage: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        stages[stage] += now - clock
        clock = now

    scene = mesh if isinstance(mesh, CollisionScene) else CollisionScene(check_mesh(mesh))
    if top_k is not None and top_k < 1:
        raise ValueError(f"top_k must be >= 1 or None, got {top_k}")
    if exact is not None and exact < 1:
        raise ValueError(f"exact must be >= 1 or None, got {exact}")
    problem = too_large(scene.mesh)
    if problem is not None:
        raise ValueError(problem)
    radius = float(np.linalg.norm(scene.mesh.extents))  # bounding-box diagonal
    travel = radius + 2.0 * STANDOFF_M if max_travel is None else max_travel
    support_plane = scene.support_plane if support_plane is None else support_plane
    scene = scene.with_support_plane(support_plane)  # the table: an obstacle to the hand
    options = {"n_candidates": n_candidates, "seed": seed, "spreads_deg": spreads_deg}
    if support_plane is None:
        candidates = candidate_poses(scene.mesh, **options)
    else:
        candidates = table_candidates(scene.mesh, support_plane, travel=travel, **options)
    lap("setup")
    screened = top_k is not None and exact is not None and exact < len(candidates)
    order = screen_order(scene, candidates, travel) if screened else list(range(len(candidates)))
    lap("screen")
    batch = len(order) if not screened else max(exact, top_k)
    done: dict[int, GraspResult] = {}
    memo: dict[int, GraspResult] = {}  # id(result) -> scored: each grasp is scored once
    position = 0
    while True:
        for i in order[position : position + batch]:
            c = candidates[i]
            limit = travel if c.travel is None else c.travel
            result = autograsp(
                scene, c.palm_pose, spread_deg=c.spread_deg, max_travel=limit, quality=False
            )
            if support_plane is None or not crosses(support_plane, result):
                done[i] = result
        position += batch
        lap("autograsp")
        results = [done[i] for i in sorted(done)]  # candidate order breaks ties
        if top_k is None:  # every candidate's result, ranked (for diagnostics): no dedup
            best = rank(results, scene)
        else:
            best = _best_distinct(results, scene, top_k, memo)
        lap("rank")
        enough = top_k is None or sum(g.success for g in best) >= top_k
        if enough or position >= len(order):
            if timings is not None:
                timings.update(stages, screened=len(candidates) if screened else 0,
                               autograsped=min(position, len(order)))
            return best


def screen_order(scene: CollisionScene, candidates: Sequence[Candidate], travel: float):
    """Candidate indices, most promising first by the screen's prediction: approaches that meet
    the object, then those where the palm touches (power grasps, :func:`rank_key`'s second key),
    then the centre of mass nearest the palm (a short lever); ties in candidate order."""
    palms = np.stack([c.palm_pose for c in candidates])
    spreads = np.array([c.spread_deg for c in candidates])
    if any(c.travel is not None for c in candidates):
        travel = np.array([travel if c.travel is None else c.travel for c in candidates])
    screen = Screen(
        scene.mesh, spacing=SCREEN_SPACING_M, nearest=True, support_plane=scene.support_plane
    )
    touches, palm, depth = screen.predict(palms, spreads, travel, scene.center)
    return sorted(range(len(candidates)), key=lambda i: (not touches[i], not palm[i], depth[i], i))


def _best_distinct(
    results: Sequence[GraspResult], scene: CollisionScene, top_k: int, memo: dict | None = None
):
    """The first ``top_k`` distinct grasps of the ranking: rank only as many as needed, widened
    while duplicates among them leave fewer than ``top_k`` (the top one is always distinct)."""
    width = top_k
    while True:
        best = distinct(rank(results, scene, top_k=width, memo=memo), top_k)
        if len(best) >= top_k or width >= len(results):
            return best
        width = min(2 * width, len(results))


def rank(
    results: Sequence[GraspResult],
    scene: CollisionScene,
    *,
    top_k: int | None = None,
    memo: dict[int, GraspResult] | None = None,
) -> list[GraspResult]:
    """Score (epsilon, volume) and sort grasps on ``scene``'s object, best first (:func:`rank_key`).

    What the ranking optimises: a grasp that holds when the object is lifted and carried.
    Force closure comes first (without it some disturbance pulls the object out whatever the
    fingers do). Then power grasps, the palm touching the object: the palm is carried by the
    arm, so the load does not have to pass through the finger motors' 1-1.3 N·m. Then the force
    epsilon (:mod:`grasp.quality`): the largest force through the centre of mass, in the worst
    direction, resisted per unit of contact force; weight and inertia are such forces. Last,
    the Ferrari–Canny epsilon. With 64 candidates on the true mesh, the top grasp by epsilon
    alone held in the lift test for 7 of the 10 named objects, by this ranking for 10 (README).

    Ties keep the input order. With ``top_k`` only the grasps that can still enter the top list
    are scored: force closure (the 6-D hull) is computed in the order of the other keys, which
    need only the contacts and the palm pose, until ``top_k`` force-closure grasps were found;
    the returned list is exactly the first ``top_k`` of the full ranking. ``memo`` (id of a
    result → its scored copy) keeps scores between calls on growing lists of the same results.
    """

    def cheap(i: int) -> tuple[bool, bool]:  # the keys that need no wrench hull
        return (bool(results[i].contacts), palm_touches(results[i]))

    scored: dict[int, GraspResult] = {}
    found, last = 0, None
    for i in sorted(range(len(results)), key=lambda i: (*cheap(i), -i), reverse=True):
        if top_k is not None and found >= top_k and cheap(i) != last:
            break  # ranks below every force-closure grasp found (ties on the cheap keys go on)
        r = results[i]
        if memo is not None and id(r) in memo:
            scored[i] = memo[id(r)]
        else:
            scored[i] = r if not math.isnan(r.epsilon) else with_quality(r, scene)
            if memo is not None:
                memo[id(r)] = scored[i]
        if scored[i].success:
            found, last = found + 1, cheap(i)
    ranked = sorted(scored, key=lambda i: (*rank_key(scored[i]), -i), reverse=True)
    return [scored[i] for i in ranked][: len(results) if top_k is None else top_k]


def read_mesh_argument(parser, path, *, scale: float = 1.0) -> trimesh.Trimesh:
    """A command-line MESH (a mesh file or an object id, :func:`completion.objects.mesh_from_spec`),
    scaled; an ``argparse`` parser error when it is missing or holds no triangles."""
    from completion.objects import mesh_from_spec

    try:
        mesh = mesh_from_spec(str(path))
    except ValueError as exc:
        parser.error(f"no such mesh file or object: {exc}")
    if scale != 1.0:
        mesh.apply_scale(scale)
    return mesh


def _plane_argument(text: str) -> SupportPlane:
    import argparse

    try:
        return SupportPlane.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m grasp.planner MESH``: plan, print the best grasps and the time taken."""
    import argparse
    from pathlib import Path

    parser = argparse.ArgumentParser(
        prog="python -m grasp.planner", description="Plan BarrettHand grasps on a mesh file."
    )
    add = parser.add_argument
    add("mesh", type=Path, help="mesh file (OBJ, STL, PLY, ...; metres) or object id (named/mug)")
    add("--candidates", type=int, default=64, help="candidate grasps to try")
    add("--seed", type=int, default=0, help="seed of the candidates")
    add("--top-k", type=int, default=5, help="grasps to print")
    add("--scale", type=float, default=1.0, help="multiply the mesh by this")
    add("--exact", type=int, default=EXACT_CANDIDATES,
        help="candidates autograsped exactly per round after the screen (0: all, no screen)")
    add("--support-plane", type=_plane_argument, default=None, metavar="NX,NY,NZ,D",
        help="the table the object rests on, n·x + d = 0 in the mesh's frame, n up: an obstacle "
        "to the hand, no approach from below")
    args = parser.parse_args(argv)
    mesh = read_mesh_argument(parser, args.mesh, scale=args.scale)
    wall, cpu = time.perf_counter(), time.process_time()
    timings: dict[str, float] = {}
    results = plan(mesh, n_candidates=args.candidates, seed=args.seed, top_k=args.top_k,
                   support_plane=args.support_plane, exact=None if args.exact == 0 else args.exact,
                   timings=timings)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    print(f"{args.mesh.name}: {len(mesh.faces)} faces, {args.candidates} candidates in "
          f"{wall:.2f} s wall, {cpu:.2f} s CPU")
    names = ("setup", "screen", "autograsp", "rank")
    stages = ", ".join(f"{name} {1000 * timings[name]:.0f} ms" for name in names)
    rate = timings["screened"] / timings["screen"] if timings["screened"] else 0.0
    print(f"stages: {stages}; screened {timings['screened']} ({rate:.0f} a second), "
          f"autograsped {timings['autograsped']}")
    for rank, r in enumerate(results, 1):
        position = ", ".join(f"{1000 * v:.0f}" for v in r.palm_pose[:3, 3])
        approach = ", ".join(f"{v:+.2f}" for v in r.palm_pose[:3, 2])
        fingers = ", ".join(f"{v:+.2f}" for v in r.palm_pose[:3, 1])
        print(
            f"{rank:2d}. eps {r.epsilon:6.3f}  volume {r.volume:7.3f}  "
            f"{'palm, ' if palm_touches(r) else ''}palm at ({position}) mm, "
            f"approach ({approach}), fingers along ({fingers})  {r.reason}"
        )
        joints = zip(JOINT_NAMES, r.joints_deg, strict=True)
        print("    " + "  ".join(f"{name} {v:.1f}°" for name, v in joints))


if __name__ == "__main__":
    main()
