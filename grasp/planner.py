"""Grasp planning: candidate palm poses around an object, autograsp each, rank by quality.

The candidates (deterministic from ``seed``) come from :mod:`grasp.candidates`: along the
object's principal axes, then from a seeded sphere of approach directions; on a table, top-down
and fingertip grasps first and none from below.

Every candidate approaches until contact. Results come back as values: a candidate that fails is a
``GraspResult`` with ``success=False`` and its reason, ranked after the successes.

Ranking (:func:`rank`): force closure first, then power grasps (the palm touching the object),
then the force epsilon (pure forces through the centre of mass), then the Ferrari–Canny epsilon
of the L1 grasp wrench space; it is chosen to predict the lift test (``grasp.physics``). The top-k
are distinct grasps: a grasp whose palm pose lies within 1 cm and 10° of a better one is left
out (:data:`DISTINCT_M`, :data:`DISTINCT_DEG`).

The search is what it says, whatever ``top_k`` is: a distance-field screen (:mod:`grasp.screen`)
predicts the approach of all ``n_candidates`` at once and orders them, the most promising
``budget`` (:data:`AUTOGRASP_BUDGET`) get the exact fcl autograsp, and all of those are ranked;
``top_k`` only says how many of the ranking come back, so ``plan(m, top_k=1)[0]`` is
``plan(m, top_k=5)[0]``. The budget is a count, not a time, so that the grasp does not depend on
the machine's load; ``budget=None`` autograsps every candidate.

A support plane (``support_plane=SupportPlane(...)``, n·x + d = 0 in the mesh's frame, n up, the
object on its upper side) is the table, an obstacle to the hand as in GraspIt!
(:mod:`grasp.autograsp`, :mod:`grasp.table`): no link goes below it.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence

import numpy as np
import trimesh

from grasp.autograsp import GraspResult, autograsp, with_quality
from grasp.candidates import (
    DEFAULT_SPREADS_DEG,
    STANDOFF_M,
    Candidate,
    candidate_poses,
    footprint,
    table_candidates,
)
from grasp.collision import CollisionScene, check_mesh
from grasp.defaults import AUTOGRASP_BUDGET as AUTOGRASP_BUDGET  # re-exported
from grasp.obstacles import Obstacles, hand_clear, hit_reason, sweep_hit
from grasp.pinch import TABLE_PINCH, pinch_failure
from grasp.screen import Screen, fingertip_span
from grasp.table import crosses
from grasp.verify import DEFAULT_VERIFY, VerifySettings, describe
from grasp.verify import verify as verify_grasps
from grasp_client.wire import SupportPlane
from hands.barrett import JOINT_NAMES

#: Largest object the planner tries, as its bounding-box diagonal (metres). The open BH8-282
#: spans about 0.3 m, so bigger shapes come back as failures (no force closure); one several
#: metres across is refused outright: approaching it in 10 mm steps would take minutes.
MAX_OBJECT_DIAGONAL_M = 2.0
#: Two grasps are the same grasp when their palm poses are closer than both of these.
DISTINCT_M = 0.01
DISTINCT_DEG = 10.0
#: Spacing of the hand's points in the planner's screen (metres): 430 points on the hand.
SCREEN_SPACING_M = 0.02
#: On a table, the fingertip candidates of an object lower than this (metres above the plane) are
#: autograsped first, whatever the screen predicts (:func:`screen_order`; chosen on training-split
#: objects: 4 to 8 cm gave the same, docs/grasping.md).
PINCH_FIRST_HEIGHT_M = 0.06
#: On a table, a force-closure grasp the lift model gives less than this chance to hold is a
#: failure that says so (:mod:`grasp.lift_model`; on the benchmark's true meshes every top grasp
#: below it dropped).
HOLD_THRESHOLD = 0.5
#: Among obstacles, a candidate whose open hand meets one, at the pre-grasp or on its way, is
#: tried again with the fingers pre-shaped to this DOF (degrees) before the approach: the open
#: BarrettHand's fingertips reach 16 cm from the palm's axis, pre-shaped ones about half that.
#: Half of the proximal's 90° to the palm plane; not tuned.
CLUTTER_PRESHAPE_DEG = 45.0

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


def plan(
    mesh: trimesh.Trimesh | CollisionScene,
    *,
    n_candidates: int = 64,
    seed: int = 0,
    top_k: int | None = 10,
    spreads_deg: Sequence[float] = DEFAULT_SPREADS_DEG,
    max_travel: float | None = None,
    support_plane: SupportPlane | None = None,
    budget: int | None = AUTOGRASP_BUDGET,
    verify: int = 0,
    verify_settings: VerifySettings = DEFAULT_VERIFY,
    obstacles: Obstacles | None = None,
    timings: dict[str, float] | None = None,
) -> list[GraspResult]:
    """Plan BarrettHand grasps on ``mesh``: the best ``top_k`` distinct grasps of
    ``n_candidates`` candidates.

    Stages: the candidates (:func:`candidate_poses`, :func:`table_candidates`); a screen that
    predicts, for every candidate at once, where its approach stops and whether the palm is
    what touches (:meth:`grasp.screen.Screen.predict`, a distance field of the mesh); the exact
    autograsp (approach, close, contacts) of the most promising ``budget`` candidates by that
    prediction; the ranking (:func:`rank`) of all of those. ``top_k`` does not change the search:
    the top grasp is the same for every ``top_k``.

    Parameters
    ----------
    mesh : trimesh.Trimesh or CollisionScene
        The object, world frame, metres.
    n_candidates : int
        Number of candidate pre-grasps (see :func:`candidate_poses`).
    seed : int
        Seed of the random candidates; the same seed gives the same plan.
    top_k : int or None
        How many distinct grasps to return, best first (None: every autograsped candidate's
        result, ranked, near-duplicates included).
    spreads_deg : sequence of float
        Spreads the random candidates choose from.
    max_travel : float or None
        Longest approach; default: through the whole bounding sphere.
    support_plane : SupportPlane or None
        The table, in the mesh's frame (default: the scene's): an obstacle to the hand; the
        candidates are then :func:`table_candidates` (none from below).
    budget : int or None
        How many candidates are autograsped exactly, most promising first by the screen (None,
        or at least ``n_candidates``: all of them, no screen).
    verify : int
        Lift-test at most this many of the best-ranked force-closure grasps on ``mesh`` itself
        (standing on the support plane, its mass estimated from it), in ``verify_settings``'s
        perturbed trials, until one holds in every trial; the grasps that held come first
        (:mod:`grasp.verify`). 0: no verification (the plan is exactly the unverified one).
    verify_settings : VerifySettings
        The trials' number and ranges (:class:`grasp.verify.VerifySettings`).
    obstacles : Obstacles or None
        What the hand must not touch besides the object and the table (the neighbours,
        :mod:`grasp.obstacles`), in the mesh's frame: a candidate whose open hand meets one at
        the pre-grasp is tried pre-shaped or not at all, and a grasp whose approach or closing
        would is refused with the reason, the screen's next candidate autograsped in its place
        (the budget counts the grasps the obstacles allow). None or empty: exactly the plan without.
    timings : dict or None
        Filled with each stage's seconds ("setup": the collision model and the candidates;
        "screen"; "autograsp"; "rank", with the quality measures; "verify") and the counts
        "screened", "autograsped" (the budget spent) and "verified" (grasps lift-tested).

    Returns
    -------
    list of GraspResult, sorted by :func:`rank_key` descending, ties in candidate order; with
    ``top_k``, without near-duplicates (:func:`distinct`).
    """
    clock = time.perf_counter()
    stages = {"setup": 0.0, "screen": 0.0, "autograsp": 0.0, "rank": 0.0, "verify": 0.0}

    def lap(stage: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        stages[stage] += now - clock
        clock = now

    scene = mesh if isinstance(mesh, CollisionScene) else CollisionScene(check_mesh(mesh))
    if top_k is not None and top_k < 1:
        raise ValueError(f"top_k must be >= 1 or None, got {top_k}")
    if budget is not None and budget < 1:
        raise ValueError(f"budget must be >= 1 or None, got {budget}")
    if isinstance(verify, bool) or not isinstance(verify, int) or verify < 0:
        raise ValueError(f"verify must be a count of grasps >= 0, got {verify!r}")
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
    blocked = []
    if obstacles is not None and len(obstacles):  # the open hand at the pre-grasp; else shaped
        blocked = _clear_at_start(obstacles, candidates)
        kept = [c for c in blocked if c is not None]
        # (every one blocked: all are tried, and refused with the reason)
        candidates = kept if kept else candidates
    lap("setup")
    screened = budget is not None and budget < len(candidates)
    ranked_order = (screen_order(scene, candidates, travel) if screened
                    else list(range(len(candidates))))
    first = sorted(ranked_order[:budget] if screened else ranked_order)  # candidate order: ties
    batch, rest = [candidates[i] for i in first], ranked_order[budget:] if screened else []
    lap("screen")
    results, spent, shaped, refusals = [], 0, [], 0
    while batch:  # a grasp the obstacles refuse does not count: the next candidates take its place
        refused = 0
        for c in batch:
            limit = travel if c.travel is None else c.travel
            result = autograsp(scene, c.palm_pose, spread_deg=c.spread_deg, max_travel=limit,
                               quality=False, pinch=c.source == TABLE_PINCH,
                               preshape_deg=c.preshape_deg)
            if support_plane is not None and crosses(support_plane, result):
                continue
            if obstacles is not None and result.contacts:
                hit = sweep_hit(obstacles, c.palm_pose, result.palm_pose, result.joints_deg,
                                end_palm_pose=result.end_palm_pose, preshape_deg=c.preshape_deg)
                if hit is not None:
                    result, refused = _refused(result, hit_reason(hit, scene.mesh)), refused + 1
                    if not c.preshape_deg and c.source != TABLE_PINCH:  # try it pre-shaped
                        shaped.append(dataclasses.replace(c, preshape_deg=CLUTTER_PRESHAPE_DEG))
            results.append(result)
        spent, refusals = spent + len(batch), refusals + refused
        take = max(refused - len(shaped), 0)  # pre-shaped retries first, then the screen's next
        batch = shaped[:refused] + [candidates[i] for i in sorted(rest[:take])]
        shaped, rest = shaped[refused:], rest[take:]
    lap("autograsp")
    # every autograsped result is ranked; top_k only cuts the list
    tried = 0
    if verify:
        ranked = distinct(rank(results, scene))
        lap("rank")
        best = verify_grasps(scene.mesh, ranked, verify, support_plane, seed, verify_settings)
        tried = sum(g.verification.tried for g in best)
        best = best if top_k is None else best[:top_k]
        lap("verify")
    elif top_k is None:
        best = rank(results, scene)
    else:
        best = _best_distinct(results, scene, top_k)
    if best and not best[0].success:
        why = [w for w in (support_plane and table_limits(scene.mesh, support_plane),
                           support_plane and pinch_failure(results),
                           obstacle_failure(blocked, refusals))
               if w and w not in best[0].reason]
        if why:
            best[0] = dataclasses.replace(best[0], reason="; ".join([best[0].reason, *why]))
    lap("rank")
    if timings is not None:
        timings.update(stages, screened=len(candidates) if screened else 0,
                       autograsped=spent, verified=tried)
    return best


def _clear_at_start(obstacles: Obstacles, candidates: Sequence[Candidate]) -> list:
    """Per candidate: itself if its open hand at the pre-grasp meets no obstacle; else itself
    pre-shaped (:data:`CLUTTER_PRESHAPE_DEG`) if that one meets none (a table pinch is never
    pre-shaped); else None."""
    palms = np.stack([c.palm_pose for c in candidates])
    spreads = np.array([c.spread_deg for c in candidates])
    opened = hand_clear(obstacles, palms, spreads)
    shaped = hand_clear(obstacles, palms, spreads, CLUTTER_PRESHAPE_DEG)
    return [c if opened[i] else dataclasses.replace(c, preshape_deg=CLUTTER_PRESHAPE_DEG)
            if shaped[i] and c.source != TABLE_PINCH else None for i, c in enumerate(candidates)]


def _refused(result: GraspResult, reason: str) -> GraspResult:
    """A grasp the obstacles rule out: no grasp, whatever its contacts (it is not scored)."""
    return dataclasses.replace(result, success=False, reason=reason, epsilon=-1.0, volume=0.0,
                               force_epsilon=-1.0)


def obstacle_failure(blocked: Sequence, refused: int) -> str | None:
    """What the obstacles ruled out, when they did (None: nothing). ``blocked``: per candidate,
    what the pre-grasp check kept (None: blocked); ``refused``: grasps refused after closing."""
    at_start = sum(c is None for c in blocked)
    if not at_start and not refused:
        return None
    return (f"obstacles: {at_start} of {len(blocked)} candidates blocked at the pre-grasp, "
            f"{refused} grasps refused")


def screen_order(scene: CollisionScene, candidates: Sequence[Candidate], travel: float):
    """Candidate indices, most promising first: on a table, the fingertip grasps of an object
    lower than :data:`PINCH_FIRST_HEIGHT_M` (at most four; the screen cannot see what their
    closing tips meet, and on a flat object they are often the only force closure), then by the
    screen's prediction: approaches that meet the object (and fingertip grasps, which stop above
    it by design), then those where the palm touches (power grasps, :func:`rank_key`'s second
    key), then the centre of mass nearest the palm (a short lever); ties in candidate order.

    Before the fingertip grasps came first, a 12 × 8 × 3 cm box lying on a table got no grasp
    at budget 16: its only force-closure candidates, the four fingertip ones, were the screen's
    19th to 22nd (docs/grasping.md has the measurements on training objects)."""
    palms = np.stack([c.palm_pose for c in candidates])
    spreads = np.array([c.spread_deg for c in candidates])
    if any(c.travel is not None for c in candidates):
        travel = np.array([travel if c.travel is None else c.travel for c in candidates])
    screen = Screen(
        scene.mesh, spacing=SCREEN_SPACING_M, nearest=True, support_plane=scene.support_plane
    )
    touches, palm, depth = screen.predict(palms, spreads, travel, scene.center)
    pinch = np.array([c.source in ("pinch", TABLE_PINCH) for c in candidates])
    touches |= pinch  # a fingertip grasp stops above a low object: its fingers meet it
    plane = scene.support_plane
    flat = plane is not None and plane.height(scene.mesh.vertices).max() < PINCH_FIRST_HEIGHT_M
    first = pinch if flat else np.zeros(len(candidates), dtype=bool)
    return sorted(range(len(candidates)),
                  key=lambda i: (not first[i], not touches[i], not palm[i], depth[i], i))


def _best_distinct(results: Sequence[GraspResult], scene: CollisionScene, top_k: int):
    """The first ``top_k`` distinct grasps of the ranking: rank only as many as needed, widened
    while duplicates among them leave fewer than ``top_k`` (the top one is always distinct)."""
    width, memo = top_k, {}  # each grasp is scored once however often the list widens
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

    On a table (``scene.support_plane``) the second key is the lift model's probability that the
    grasp holds (:mod:`grasp.lift_model`, learned from lift tests on training-split objects: the
    object's estimated weight against the grip, the grasp's kind, its contacts' heights); every
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
                scored[i] = _with_hold_probability(scored[i], scene)
            if memo is not None:
                memo[id(r)] = scored[i]
        if scored[i].success:
            found, last = found + 1, cheap(i)
    ranked = sorted(scored, key=lambda i: (*rank_key(scored[i]), -i), reverse=True)
    return [scored[i] for i in ranked][: len(results) if top_k is None else top_k]


def _with_hold_probability(result: GraspResult, scene: CollisionScene) -> GraspResult:
    """A scored force-closure grasp on a table with the lift model's probability that it holds;
    below :data:`HOLD_THRESHOLD` it is a failure that says so."""
    from grasp.lift_model import DENSITY_KG_M3, estimated_mass, features, hold_probability

    mass = estimated_mass(scene.mesh)
    p = float(hold_probability(features(result, scene.mesh, scene.support_plane, mass=mass))[0])
    if p >= HOLD_THRESHOLD or math.isnan(p):
        return dataclasses.replace(result, hold_probability=p)
    reason = (f"force closure, but predicted to drop when lifted (hold probability {p:.2f}; "
              f"{mass:.2f} kg estimated at {DENSITY_KG_M3:g} kg/m³)")
    return dataclasses.replace(result, hold_probability=p, success=False, reason=reason)


def table_limits(mesh: trimesh.Trimesh, plane: SupportPlane) -> str | None:
    """Why the hand may find no grasp of ``mesh`` on ``plane``: its footprint is wider than what
    the fingertips close to from above (:func:`grasp.screen.fingertip_span`); None otherwise."""
    narrow, long, height = footprint(mesh, plane)
    span = fingertip_span()
    if narrow <= span:
        return None
    return (f"the object is {100 * narrow:.0f} × {100 * long:.0f} cm on the table and "
            f"{100 * height:.0f} cm tall: wider than the {100 * span:.0f} cm the fingertips "
            f"close to from above")


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

    from completion.cli import HelpWithDefaults

    parser = argparse.ArgumentParser(formatter_class=HelpWithDefaults,
        prog="python -m grasp.planner", description="Plan BarrettHand grasps on a mesh file."
    )
    add = parser.add_argument
    add("mesh", type=Path, help="mesh file (OBJ, STL, PLY, ...; metres) or object id (named/mug)")
    add("--candidates", type=int, default=64, help="candidate grasps to try")
    add("--seed", type=int, default=0, help="seed of the candidates")
    add("--top-k", type=int, default=5, help="grasps to print")
    add("--scale", type=float, default=1.0, help="multiply the mesh by this")
    add("--budget", type=int, default=AUTOGRASP_BUDGET,
        help=f"candidates autograsped exactly, the screen's most promising first (0: all, no "
        f"screen; default {AUTOGRASP_BUDGET})")
    add("--verify", type=int, default=0, metavar="N",
        help="lift-test at most N of the best grasps on the mesh before answering, until one "
        "holds in every trial (0: none)")
    add("--support-plane", type=_plane_argument, default=None, metavar="NX,NY,NZ,D",
        help="the table the object rests on (default: none), n·x + d = 0 in the mesh's frame, "
        "n up: an obstacle to the hand, no approach from below")
    args = parser.parse_args(argv)
    if args.verify < 0:
        parser.error(f"--verify must be >= 0, got {args.verify}")
    mesh = read_mesh_argument(parser, args.mesh, scale=args.scale)
    wall, cpu = time.perf_counter(), time.process_time()
    timings: dict[str, float] = {}
    results = plan(mesh, n_candidates=args.candidates, seed=args.seed, top_k=args.top_k,
                   support_plane=args.support_plane, budget=args.budget or None,
                   verify=args.verify, timings=timings)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    print(f"{args.mesh.name}: {len(mesh.faces)} faces, {args.candidates} candidates in "
          f"{wall:.2f} s wall, {cpu:.2f} s CPU")
    names = ("setup", "screen", "autograsp", "rank") + (("verify",) if args.verify else ())
    stages = ", ".join(f"{name} {1000 * timings[name]:.0f} ms" for name in names)
    rate = timings["screened"] / timings["screen"] if timings["screened"] else 0.0
    print(f"stages: {stages}; screened {timings['screened']} ({rate:.0f} a second), "
          f"autograsped {timings['autograsped']}"
          + (f", lift-tested {timings['verified']}" if args.verify else ""))
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
        if r.verification is not None:
            print(f"    {describe(r.verification)}")


if __name__ == "__main__":
    main()
