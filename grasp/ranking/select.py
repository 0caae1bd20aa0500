"""The grasps a plan returns: ranked, distinct, and with ``verify=N`` lift-tested in physics
first. One composition for the CLI, the service and the evaluation (docs/design.md §7)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import trimesh

from grasp.hand.collision import CollisionScene
from grasp.hand.result import GraspResult
from grasp.physics.verify import DEFAULT_VERIFY, Outcome, VerifySettings, verify
from grasp.ranking.rank import HOLD_THRESHOLD, best_distinct, distinct, rank
from grasp_client.wire import SupportPlane


def select(
    results: Sequence[GraspResult], scene: CollisionScene, *, top_k: int | None,
    verify: int = 0, seed: int = 0, verify_settings: VerifySettings = DEFAULT_VERIFY,
    lap: Callable[..., None] = lambda stage, **counts: None, min_hold: float = HOLD_THRESHOLD,
) -> list[GraspResult]:
    """The best ``top_k`` distinct grasps of ``results`` on ``scene`` (None: every result,
    ranked, near-duplicates included; on a table, those under ``min_hold`` hold probability
    count as failures); with ``verify``, the distinct ranking lift-tested by :func:`verified`
    before the cut. ``lap(stage, **counts)`` is called after "rank" (and "verify", with
    ``verified``: how many grasps were lift-tested)."""
    if not verify:
        best = (rank(results, scene, min_hold=min_hold) if top_k is None
                else best_distinct(results, scene, top_k, min_hold))
        lap("rank")
        return best
    ranked = rank(results, scene, min_hold=min_hold)
    lap("rank")
    best = verified(ranked, verify, mesh=scene.mesh, support_plane=scene.support_plane,
                    seed=seed, settings=verify_settings)
    lap("verify", verified=sum(g.verification.tried for g in best))
    return best if top_k is None else best[:top_k]


def verified(
    ranked: Sequence[GraspResult], n: int, *, mesh: trimesh.Trimesh | None,
    support_plane: SupportPlane | None, seed: int, settings: VerifySettings = DEFAULT_VERIFY,
    run: Callable[[Iterable], Iterable[Outcome]] | None = None,
) -> list[GraspResult]:
    """The distinct grasps of a ranking, at most ``n`` of the best lift-tested on ``mesh`` until
    one holds in every trial, those that held first (:func:`grasp.physics.verify.verify`; ``run``
    maps its trials, e.g. onto a worker pool, where ``mesh`` may be None)."""
    return verify(mesh, distinct(ranked), n, support_plane, seed, settings, run=run)
