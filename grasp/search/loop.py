"""The budgeted autograsp loop: the candidates, the screen's order, the exact autograsp of the
most promising ``budget`` of them, the obstacles' refusals replaced by the next candidates.

The budget is a count, not a time, so that the grasp does not depend on the machine's load.
A candidate whose open hand meets an obstacle at the pre-grasp is tried pre-shaped
(:data:`CLUTTER_PRESHAPE_DEG`) or not at all; a grasp whose approach or closing meets one is
refused with the reason and does not count: a pre-shaped retry of it, then the screen's next
candidate, takes its place.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import trimesh

from grasp.hand.autograsp import autograsp
from grasp.hand.collision import CollisionScene
from grasp.hand.pinch import TABLE_PINCH, pinch_failure
from grasp.hand.result import GraspResult
from grasp.hand.table import crosses
from grasp.search.candidates import Candidate, candidate_poses, footprint, table_candidates
from grasp.search.obstacles import Obstacles, hand_clear, hit_reason, sweep_hit
from grasp.search.screen import Screen, fingertip_span
from grasp_client.wire import SupportPlane

#: Spacing of the hand's points in the planner's screen (metres): 430 points on the hand.
SCREEN_SPACING_M = 0.02
#: On a table, the fingertip candidates of an object lower than this (metres above the plane) are
#: autograsped first, whatever the screen predicts (:func:`screen_order`; chosen on training-split
#: objects: 4 to 8 cm gave the same, docs/grasping.md).
PINCH_FIRST_HEIGHT_M = 0.06
#: Among obstacles, a candidate whose open hand meets one, at the pre-grasp or on its way, is
#: tried again with the fingers pre-shaped to this DOF (degrees) before the approach: the open
#: BarrettHand's fingertips reach 16 cm from the palm's axis, pre-shaped ones about half that.
#: Half of the proximal's 90° to the palm plane; not tuned.
CLUTTER_PRESHAPE_DEG = 45.0


@dataclass(frozen=True)
class Searched:
    """What the search autograsped (``results``, candidate order within each round) and what the
    obstacles ruled out: per candidate what the pre-grasp check kept (None: blocked; empty without
    obstacles), and how many grasps they refused after closing."""

    results: list[GraspResult]
    blocked: list
    refused: int

    def failure_reasons(self, scene: CollisionScene) -> list[str]:
        """Why the search may have found no grasp: the table's limits, the pinch's, the
        obstacles' (each only when it applies)."""
        plane = scene.support_plane
        why = (plane and table_limits(scene.mesh, plane), plane and pinch_failure(self.results),
               obstacle_failure(self.blocked, self.refused))
        return [w for w in why if w]


def search(
    scene: CollisionScene, *, n_candidates: int, seed: int, spreads_deg: Sequence[float],
    travel: float, budget: int | None, obstacles: Obstacles | None,
    lap: Callable[..., None] = lambda stage, **counts: None,
) -> Searched:
    """Autograsp the most promising ``budget`` of ``n_candidates`` candidates on ``scene`` (its
    support plane, if any, is the table), as :func:`grasp.planner.plan` describes; ``lap(stage,
    **counts)`` is called after "setup", "screen" (``screened``: candidates the screen ordered, 0
    for none) and "autograsp" (``autograsped``: the budget spent)."""
    options = {"n_candidates": n_candidates, "seed": seed, "spreads_deg": spreads_deg}
    plane = scene.support_plane
    if plane is None:
        candidates = candidate_poses(scene.mesh, **options)
    else:
        candidates = table_candidates(scene.mesh, plane, travel=travel, **options)
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
    lap("screen", screened=len(candidates) if screened else 0)
    results, spent, shaped, refusals = [], 0, [], 0
    while batch:  # a grasp the obstacles refuse does not count: the next candidates take its place
        refused = 0
        for c in batch:
            tried = _autograsp(scene, c, travel, obstacles)
            if tried is None:
                continue
            result, was_refused = tried
            if was_refused:
                refused += 1
                if not c.preshape_deg and c.source != TABLE_PINCH:  # try it pre-shaped
                    shaped.append(dataclasses.replace(c, preshape_deg=CLUTTER_PRESHAPE_DEG))
            results.append(result)
        spent, refusals = spent + len(batch), refusals + refused
        take = max(refused - len(shaped), 0)  # pre-shaped retries first, then the screen's next
        batch = shaped[:refused] + [candidates[i] for i in sorted(rest[:take])]
        shaped, rest = shaped[refused:], rest[take:]
    lap("autograsp", autograsped=spent)
    return Searched(results, blocked, refusals)


def _autograsp(scene: CollisionScene, c: Candidate, travel: float,
               obstacles: Obstacles | None) -> tuple[GraspResult, bool] | None:
    """One candidate's exact autograsp (no quality yet: the ranking scores it) and whether the
    obstacles refused it (then it is a failure with their reason); None when a link crossed the
    table."""
    limit = travel if c.travel is None else c.travel
    result = autograsp(scene, c.palm_pose, spread_deg=c.spread_deg, max_travel=limit,
                       quality=False, pinch=c.source == TABLE_PINCH, preshape_deg=c.preshape_deg)
    if scene.support_plane is not None and crosses(scene.support_plane, result):
        return None
    if obstacles is not None and result.contacts:
        hit = sweep_hit(obstacles, c.palm_pose, result.palm_pose, result.joints_deg,
                        end_palm_pose=result.end_palm_pose, preshape_deg=c.preshape_deg)
        if hit is not None:
            return _refused(result, hit_reason(hit, scene.mesh)), True
    return result, False


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


def table_limits(mesh: trimesh.Trimesh, plane: SupportPlane) -> str | None:
    """Why the hand may find no grasp of ``mesh`` on ``plane``: its footprint is wider than what
    the fingertips close to from above (:func:`grasp.search.screen.fingertip_span`); None
    otherwise."""
    narrow, long, height = footprint(mesh, plane)
    span = fingertip_span()
    if narrow <= span:
        return None
    return (f"the object is {100 * narrow:.0f} × {100 * long:.0f} cm on the table and "
            f"{100 * height:.0f} cm tall: wider than the {100 * span:.0f} cm the fingertips "
            f"close to from above")
