"""Grasp planning: candidate palm poses around an object, autograsp each, rank by quality.

:func:`plan` orchestrates three stages, each in its folder: the search (:mod:`grasp.search`:
the candidates, deterministic from ``seed``, along the object's principal axes and from a seeded
sphere of approach directions, on a table top-down and fingertip grasps first and none from below;
a distance-field screen that orders them; the exact autograsp of the most promising ``budget``),
the ranking (:mod:`grasp.ranking`: force closure, hold probability on a table, power grasps, the
force epsilon, epsilon; distinct grasps) and, with ``verify=N``, the lift test in physics
(:mod:`grasp.physics.verify`). The options are one frozen :class:`PlanOptions`.

Every candidate approaches until contact. Results come back as values: a candidate that fails is a
``GraspResult`` with ``success=False`` and its reason, ranked after the successes.

The search is what it says, whatever ``top_k`` is: the screen predicts the approach of all
``n_candidates`` at once and orders them, the most promising ``budget`` (:data:`AUTOGRASP_BUDGET`)
get the exact fcl autograsp, and all of those are ranked; ``top_k`` only says how many of the
ranking come back, so ``plan(m, top_k=1)[0]`` is ``plan(m, top_k=5)[0]``. The budget is a count,
not a time, so that the grasp does not depend on the machine's load; ``budget=None`` autograsps
every candidate.

A support plane (``support_plane=SupportPlane(...)``, n·x + d = 0 in the mesh's frame, n up, the
object on its upper side) is the table, an obstacle to the hand as in GraspIt!
(:mod:`grasp.hand.autograsp`, :mod:`grasp.hand.table`): no link goes below it.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh

from grasp.defaults import AUTOGRASP_BUDGET
from grasp.hand.autograsp import pregrasp_pose
from grasp.hand.collision import CollisionScene, check_mesh
from grasp.hand.result import GraspResult
from grasp.hand.table import hand_primitives
from grasp.physics.verify import DEFAULT_VERIFY, VerifySettings
from grasp.ranking.rank import HOLD_THRESHOLD, palm_touches
from grasp.ranking.select import select
from grasp.search.candidates import DEFAULT_SPREADS_DEG, STANDOFF_M
from grasp.search.loop import search
from grasp.search.obstacles import Obstacles
from grasp_client.wire import JOINT_NAMES, Contact, Grasp, Primitive, SupportPlane

#: Largest object the planner tries, as its bounding-box diagonal (metres). The open BH8-282
#: spans about 0.3 m, so bigger shapes come back as failures (no force closure); one several
#: metres across is refused outright: approaching it in 10 mm steps would take minutes.
MAX_OBJECT_DIAGONAL_M = 2.0


@dataclass(frozen=True)
class PlanOptions:
    """How :func:`plan` searches, ranks and verifies; checked when built.

    Attributes
    ----------
    n_candidates : int
        Number of candidate pre-grasps (:func:`grasp.search.candidates.candidate_poses`).
    seed : int
        Seed of the random candidates (and of the verification's trials); the same seed gives the
        same plan.
    top_k : int or None
        How many distinct grasps to return, best first (None: every autograsped candidate's
        result, ranked, near-duplicates included).
    spreads_deg : sequence of float
        Spreads the random candidates choose from.
    max_travel : float or None
        Longest approach; default: through the whole bounding sphere.
    support_plane : SupportPlane or None
        The table, in the mesh's frame (default: the scene's): an obstacle to the hand; the
        candidates are then :func:`grasp.search.candidates.table_candidates` (none from below).
    budget : int or None
        How many candidates are autograsped exactly, most promising first by the screen (None,
        or at least ``n_candidates``: all of them, no screen).
    verify : int
        Lift-test at most this many of the best-ranked force-closure grasps on the mesh itself
        (standing on the support plane, its mass estimated from it), in ``verify_settings``'s
        perturbed trials, until one holds in every trial; the grasps that held come first
        (:mod:`grasp.physics.verify`). 0: no verification (the plan is exactly the unverified one).
    verify_settings : VerifySettings
        The trials' number and ranges (:class:`grasp.physics.verify.VerifySettings`).
    obstacles : Obstacles or None
        What the hand must not touch besides the object and the table (the neighbours,
        :mod:`grasp.search.obstacles`), in the mesh's frame: a candidate whose open hand meets one
        at the pre-grasp is tried pre-shaped or not at all, and a grasp whose approach or closing
        would is refused with the reason, the screen's next candidate autograsped in its place
        (the budget counts the grasps the obstacles allow). None or empty: exactly the plan
        without.
    min_hold : float
        On a table, a force-closure grasp the lift model gives a lower chance to hold is a
        failure that says so (default :data:`grasp.ranking.rank.HOLD_THRESHOLD`, 0.5); lower it
        (``min_hold=0.3``) to get such grasps back with their ``hold_probability`` and decide
        yourself, or lift-test them first (``verify``).
    """

    n_candidates: int = 64
    seed: int = 0
    top_k: int | None = 10
    spreads_deg: Sequence[float] = DEFAULT_SPREADS_DEG
    max_travel: float | None = None
    support_plane: SupportPlane | None = None
    budget: int | None = AUTOGRASP_BUDGET
    verify: int = 0
    verify_settings: VerifySettings = DEFAULT_VERIFY
    obstacles: Obstacles | None = None
    min_hold: float = HOLD_THRESHOLD

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_hold <= 1.0:
            raise ValueError(f"min_hold must be a probability in [0, 1], got {self.min_hold}")
        if self.top_k is not None and self.top_k < 1:
            raise ValueError(f"top_k must be >= 1 or None, got {self.top_k}")
        if self.budget is not None and self.budget < 1:
            raise ValueError(f"budget must be >= 1 or None, got {self.budget}")
        if isinstance(self.verify, bool) or not isinstance(self.verify, int) or self.verify < 0:
            raise ValueError(f"verify must be a count of grasps >= 0, got {self.verify!r}")


def plan(
    mesh: trimesh.Trimesh | CollisionScene,
    options: PlanOptions | None = None,
    *,
    timings: dict[str, float] | None = None,
    **fields,
) -> list[GraspResult]:
    """Plan BarrettHand grasps on ``mesh`` (the object, world frame, metres): the best ``top_k``
    distinct grasps of ``n_candidates`` candidates.

    ``options`` (default :class:`PlanOptions`), with any of its fields given as keywords instead
    (``plan(mesh, top_k=1, seed=3)``). Stages: the search (:func:`grasp.search.loop.search`), the
    ranking of everything it autograsped and, with ``verify``, the lift test
    (:func:`grasp.ranking.select.select`). ``top_k`` does not change the search: the top grasp is
    the same for every ``top_k``. ``timings`` is filled with each stage's seconds ("setup": the
    collision model and the candidates; "screen"; "autograsp"; "rank", with the quality measures;
    "verify") and the counts "screened", "autograsped" (the budget spent) and "verified" (grasps
    lift-tested).

    Returns the grasps sorted by :func:`grasp.ranking.rank.rank_key` descending, ties in candidate
    order; with ``top_k``, without near-duplicates (:func:`grasp.ranking.rank.distinct`). When the
    best is no grasp, its reason also says what limited the search (the table, the pinch, the
    obstacles).
    """
    o = dataclasses.replace(options or PlanOptions(), **fields)
    lap = _Stopwatch()
    scene = mesh if isinstance(mesh, CollisionScene) else CollisionScene(check_mesh(mesh))
    problem = too_large(scene.mesh)
    if problem is not None:
        raise ValueError(problem)
    radius = float(np.linalg.norm(scene.mesh.extents))  # bounding-box diagonal
    travel = radius + 2.0 * STANDOFF_M if o.max_travel is None else o.max_travel
    plane = scene.support_plane if o.support_plane is None else o.support_plane
    scene = scene.with_support_plane(plane)  # the table: an obstacle to the hand
    searched = search(scene, n_candidates=o.n_candidates, seed=o.seed, spreads_deg=o.spreads_deg,
                      travel=travel, budget=o.budget, obstacles=o.obstacles, lap=lap)
    best = select(searched.results, scene, top_k=o.top_k, verify=o.verify, seed=o.seed,
                  verify_settings=o.verify_settings, lap=lap, min_hold=o.min_hold)
    if best and not best[0].success:
        why = [w for w in searched.failure_reasons(scene) if w not in best[0].reason]
        if why:
            best[0] = dataclasses.replace(best[0], reason="; ".join([best[0].reason, *why]))
    lap("rank")
    if timings is not None:
        timings.update(lap.stages, **lap.counts)
    return best


def too_large(mesh: trimesh.Trimesh) -> str | None:
    """Why the hand cannot grasp ``mesh`` at all (None when it may)."""
    diagonal = float(np.linalg.norm(mesh.extents))
    if diagonal <= MAX_OBJECT_DIAGONAL_M:
        return None
    return (
        f"the shape is {diagonal:.3g} m across (bounding-box diagonal), far beyond the "
        f"BarrettHand's reach; the planner tries shapes up to {MAX_OBJECT_DIAGONAL_M:g} m"
    )


class _Stopwatch:
    """``lap(stage, **counts)``: the seconds since the last lap added to ``stage``; the counts
    kept."""

    def __init__(self) -> None:
        self.stages = dict.fromkeys(("setup", "screen", "autograsp", "rank", "verify"), 0.0)
        self.counts = {"screened": 0, "autograsped": 0, "verified": 0}
        self._clock = time.perf_counter()

    def __call__(self, stage: str, **counts: int) -> None:
        now = time.perf_counter()
        self.stages[stage] += now - self._clock
        self._clock = now
        self.counts.update(counts)


def wire_grasp(result: GraspResult, camera_to_world: np.ndarray | None = None) -> Grasp:
    """The wire form of a planned grasp (:class:`grasp_client.wire.Grasp`, what ``GET /grasp``
    answers): its poses in the mesh's frame and, given ``camera_to_world``, in the world; the
    pre-grasp pose (:func:`grasp.hand.autograsp.pregrasp_pose`), the quality, the contacts and
    the hand's links placed as primitives (:func:`grasp.hand.table.hand_primitives`)."""
    palm = np.asarray(result.palm_pose, dtype=np.float64)
    before = pregrasp_pose(palm)
    end = np.asarray(result.end_palm_pose, dtype=np.float64)
    world = None if camera_to_world is None else np.asarray(camera_to_world, dtype=np.float64)
    return Grasp(
        palm_pose=palm,
        palm_pose_world=None if world is None else world @ palm,
        pregrasp_pose=before,
        pregrasp_pose_world=None if world is None else world @ before,
        joints_deg=dict(zip(JOINT_NAMES, map(float, result.joints_deg), strict=True)),
        dofs_deg=np.asarray(result.dofs_deg, dtype=np.float64),
        epsilon=float(result.epsilon),
        volume=float(result.volume),
        force_epsilon=float(result.force_epsilon),
        palm_contact=palm_touches(result),
        approach_stop=result.approach_stop,
        hold_probability=None if math.isnan(result.hold_probability)
        else float(result.hold_probability),
        verification=result.verification,
        contacts=[Contact(c.link, np.asarray(c.point, dtype=np.float64),
                          np.asarray(c.normal, dtype=np.float64)) for c in result.contacts],
        hand=[Primitive(link, kind, [float(v) for v in size], pose)
              for link, kind, size, pose in hand_primitives(result)],
        kind=result.kind,
        wrist_rise=result.wrist_rise,
        preshape_deg=float(result.preshape_deg),
        end_palm_pose=end,
        end_palm_pose_world=None if world is None else world @ end,
    )
