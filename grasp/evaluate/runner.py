"""The per-sequence work of an evaluation and the pool that runs it.

One :class:`Job` is one generated sequence. :class:`Evaluator` (one per worker process) renders
it, runs every row over it, scores each view (Jaccard against the 40³ target, F-score against the
true objects' surfaces, and the same F-score of the target itself: the ceiling), grasps the final
view of single-object sequences and lift-tests some of those grasps in pybullet.
"""

from __future__ import annotations

import numpy as np

from completion import grid as G
from completion.bullet import quiet_fds
from completion.scenes import (
    SINGLE_OBJECT_CONDITIONS,
    Sequence,
    object_meshes_in_camera,
)
from grasp.evaluate.config import (
    TRUE_MESH,
    Job,
    Settings,
    figure_rows,
)
from grasp.evaluate.rows import load_models, make_rows
from grasp.evaluate.sequence_result import SequenceResult, StageClock, Timings, key_seed
from grasp.evaluate.tables import BY_NAME, TABLES, check_options
from grasp_client.wire import SupportPlane

# ------------------------------------------------------------------------------ per-sequence work


def truth_mesh_in_latest_camera(seq: Sequence):
    """The true object mesh (single-object sequences) posed in the final view's camera frame."""
    ids = seq.meta["object_ids"]
    if len(ids) != 1:
        raise ValueError(f"the grasp ground truth needs a single-object sequence, got {ids}")
    return object_meshes_in_camera(seq, len(seq) - 1)[0]


def below_plane(occupied: np.ndarray, seq: Sequence, view: int) -> float:
    """The share of ``occupied`` voxels (a 40³ bool grid of view ``view``) whose centre lies
    below the scene's support plane (``meta["support_plane"]``, world frame); 0 when empty."""
    return _share(occupied, table_voxels(seq, view))


def table_voxels(seq: Sequence, view: int) -> np.ndarray:
    """(40, 40, 40) bool: view ``view``'s voxels whose centre lies below the scene's support
    plane (what the service cuts)."""
    plane = SupportPlane.from_values(seq.meta["support_plane"]).transformed(
        seq.camera_to_world[view])
    return G.voxels_below_plane(seq.grid_to_camera[view], plane)


def _share(occupied: np.ndarray, below: np.ndarray) -> float:
    n = int(occupied.sum())
    return int((occupied & below).sum()) / n if n else 0.0


class Evaluator:
    """Owns what a worker keeps between sequences: a renderer, the loaded models, the rows."""

    def __init__(self, settings: Settings) -> None:
        from completion.depth_camera import Renderer

        self.settings = settings
        self.renderer = Renderer()
        self.models = load_models(settings)  # the checkpoints, by name (the benchmark's too)
        self.rows = make_rows(settings, self.models)

    def close(self) -> None:
        self.renderer.close()

    def threshold(self, row: str, condition: str) -> float:
        return self.rows[row].threshold(condition)

    def probabilities(self, seq: Sequence) -> dict[str, np.ndarray]:
        """row -> (L, 40, 40, 40) occupancy probabilities (bool for the fusion reference)."""
        return {name: row.probabilities(seq) for name, row in self.rows.items()}

    def evaluate(self, job: Job) -> SequenceResult:
        """One job, its table's way (:data:`grasp.evaluate.tables.TABLES`)."""
        return BY_NAME[job.table].run(self, job)

    def sequence(self, job: Job, *, keep=None) -> SequenceResult:
        """Generate the job's sequence, run every row over it and score it: each view (Jaccard,
        F-score and its ceiling, the share below a table), the final view's grasps (and lift
        tests), the figures' example. ``keep(seq)`` False: generated, not scored."""
        timings = Timings()
        clock = StageClock(timings)
        seq = self.generate(job)
        clock.charge("generation")
        ids, elevation = list(seq.meta["object_ids"]), list(seq.meta["elevation_deg"])
        if keep is not None and not keep(seq):
            return SequenceResult(job, ids, {}, timings=timings, elevation_deg=elevation)
        probs = self.probabilities(seq)
        clock.charge("inference")
        thresholds = {row: self.threshold(row, job.condition) for row in self.settings.rows}
        per_view, ceiling = self._score_views(job, seq, probs, thresholds)
        clock.charge("completion_metrics")
        grasps, physics = self._grasps(job, seq, probs, thresholds, clock)
        clock.charge("grasping")
        example = self._example(seq, probs, thresholds, grasps) if job.example else None
        return SequenceResult(job, ids, per_view, grasps, timings, example, physics, ceiling,
                              elevation_deg=elevation)

    def generate(self, job: Job) -> Sequence:
        from completion.scenes import make_sequence

        s = self.settings
        return make_sequence(job.condition, job.split, job.index, s.seed, views=s.views,
                             pool=list(job.pool) if job.pool is not None else None,
                             noise=job.noise, renderer=self.renderer)

    def _score_views(self, job: Job, seq: Sequence, probs: dict, thresholds: dict):
        """row -> metric -> per view; and the target's own scores (the ceiling)."""
        from grasp.evaluate import metrics

        s = self.settings
        per_view = {row: {"jaccard": [], "fscore_1": [], "fscore_2": []} for row in s.rows}
        ceiling: dict[str, list[float]] = {"fscore_1": [], "fscore_2": []}
        plane = "support_plane" in seq.meta
        for v in range(len(seq)):
            below = table_voxels(seq, v) if plane else None
            for row in s.rows:
                occupied = probs[row][v] >= thresholds[row]
                per_view[row]["jaccard"].append(metrics.jaccard(occupied, seq.targets[v]))
                if below is not None:  # and as the service returns it: cut at the table
                    per_view[row].setdefault("below_plane", []).append(_share(occupied, below))
                    per_view[row].setdefault("jaccard_cut", []).append(
                        metrics.jaccard(occupied & ~below, seq.targets[v]))
            if below is not None:  # the target's own share: voxels the surface cuts
                ceiling.setdefault("below_plane", []).append(_share(seq.targets[v], below))
            if job.light or job.grasp_only:
                continue
            seed = key_seed(s.seed, job.table, job.condition, job.split, job.index, v)
            transform = seq.grid_to_camera[v]
            truth = metrics.truth_surface_sample(
                object_meshes_in_camera(seq, v), transform, seed=seed
            )
            # every prediction, and the target, sampled with one seed independent of the truth's
            scores = metrics.fscore_grids(
                seq.targets[v], truth, transform, threshold=0.5, seed=seed + 1
            )
            ceiling["fscore_1"].append(scores[0].fscore)
            ceiling["fscore_2"].append(scores[1].fscore)
            for row in s.rows:
                p, thr = probs[row][v], thresholds[row]
                scores = metrics.fscore_grids(p, truth, transform, threshold=thr, seed=seed + 1)
                per_view[row]["fscore_1"].append(scores[0].fscore)
                per_view[row]["fscore_2"].append(scores[1].fscore)
        return per_view, ceiling

    def _grasps(self, job: Job, seq: Sequence, probs: dict, thresholds: dict, clock):
        """row -> the final view's joint error; row -> lift test (physics jobs). The object
        alone, whatever the condition: the tabletop's table is not given to the planner, the
        re-grasps or the lift test (the paper's protocol, so that the conditions compare; the
        benchmark and the clutter table grasp on a table; results.md says so)."""
        from grasp.evaluate import metrics
        from grasp.hand.collision import CollisionScene

        grasps: dict[str, dict] = {}
        physics: dict[str, dict] = {}
        if not job.grasp or job.light or job.condition not in SINGLE_OBJECT_CONDITIONS:
            return grasps, physics
        s = self.settings
        truth_mesh = truth_mesh_in_latest_camera(seq)
        truth_scene = CollisionScene(truth_mesh)  # built once, reused
        seed = key_seed(s.seed, job.table, job.condition, job.split, job.index, "grasp")
        planned = {}
        for row in s.rows:
            mesh = metrics.mesh_or_none(
                probs[row][-1], seq.grid_to_camera[-1], threshold=thresholds[row]
            )
            result = metrics.grasp_joint_error(
                mesh, truth_scene, n_candidates=s.candidates, seed=seed
            )
            grasps[row] = result.as_dict()
            planned[row] = result.planned
        clock.charge("grasping")
        if job.physics:
            physics = self._lift_tests(job, truth_mesh, truth_scene, planned, seed)
            clock.charge("physics")
        return grasps, physics

    def _example(self, seq: Sequence, probs: dict, thresholds: dict, grasps: dict) -> dict:
        """The final view's grids for the figures."""
        rows = self.settings.rows
        return {
            "input": np.packbits(seq.inputs[-1]),
            "target": np.packbits(seq.targets[-1]),
            "grid_to_camera": seq.grid_to_camera[-1],
            "camera_to_world": seq.camera_to_world[-1],
            "object_to_world": seq.meta["object_to_world"][-1],
            "rows": {r: np.packbits(probs[r][-1] >= thresholds[r]) for r in rows},
            "probabilities": {r: probs[r][-1] for r in figure_rows(list(grasps))},
            "thresholds": thresholds,
        }

    def _lift_tests(self, job: Job, truth, truth_scene, planned: dict, plan_seed: int) -> dict:
        """row -> lift test of the grasp planned on that row's prediction; TRUE_MESH -> of a
        grasp planned on the true mesh. Every grasp is executed the same way, on the true object
        with a guarded approach (move in until contact), so the true-mesh row differs from the
        model rows only in the shape it was planned on."""
        from grasp.physics.lift import lift_test
        from grasp.planner import plan

        s = self.settings
        seed = key_seed(s.seed, job.table, job.condition, job.split, job.index, "physics")

        def run(grasp) -> dict:
            if grasp is None:
                return {"success": False, "reason": "no grasp planned"}
            with quiet_fds(1):
                r = lift_test(truth, grasp, seed=seed, approach="guarded")
            return {
                "success": bool(r.success),
                "reason": r.reason,
                "displacement": round(float(r.displacement), 6),
                "held_s": round(float(r.held_s), 4),
            }

        out = {row: run(planned[row]) for row in s.rows}
        best = plan(truth_scene, n_candidates=s.candidates, seed=plan_seed, top_k=1)
        out[TRUE_MESH] = run(best[0] if best else None)
        return out


# ------------------------------------------------------------------------------ planning the run


def make_jobs(settings: Settings) -> list[Job]:
    """Every sequence of the run, in a fixed order (results do not depend on the workers): each
    table's of :data:`grasp.evaluate.tables.TABLES` in turn."""
    check_options(settings)
    return [job for table in TABLES for job in table.jobs(settings)]
