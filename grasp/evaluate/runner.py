"""The per-sequence work of an evaluation and the pool that runs it.

One :class:`Job` is one generated sequence. :class:`Evaluator` (one per worker process) renders
it, runs every row over it, scores each view (Jaccard against the 40³ target, F-score against the
true objects' surfaces, and the same F-score of the target itself: the ceiling), grasps the final
view of single-object sequences and lift-tests some of those grasps in pybullet.
"""

from __future__ import annotations

import time
import zlib
from dataclasses import dataclass, field

import numpy as np

from completion import grid as G
from completion.bullet import quiet_fds
from completion.objects import object_ids
from completion.scenes import (
    NOISY_BY_DEFAULT,
    SINGLE_OBJECT_CONDITIONS,
    Sequence,
    object_meshes_in_camera,
)
from grasp.evaluate.config import (
    BENCHMARK_TABLE,
    EVAL_SPLITS,
    FOLDER_TABLE,
    FUSION,
    MAIN_TABLE,
    NAMED_OBJECTS_TABLE,
    OBJECT_TABLE_CONDITION,
    OVERHEAD_MIN_ELEVATION_DEG,
    OVERHEAD_TABLE,
    SENSOR_TABLE,
    TRUE_MESH,
    Job,
    Settings,
    figure_rows,
)
from grasp.evaluate.rows import load_models, make_rows

STAGES: tuple[str, ...] = (
    "generation",
    "inference",
    "completion_metrics",
    "grasping",
    "physics",
    "benchmark",
)


@dataclass
class Timings:
    """Seconds per stage, summed over sequences: wall clock and this process's CPU time.

    The CPU time does not grow when other jobs compete for the cores, so it is the measure to
    size runs by (a run on N free cores takes about total CPU / N).
    """

    wall: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    cpu: dict[str, float] = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))

    def add(self, other: Timings) -> None:
        for stage in STAGES:
            self.wall[stage] += other.wall[stage]
            self.cpu[stage] += other.cpu[stage]


class _StageClock:
    """Charges the wall and CPU time since the previous call to a stage of a :class:`Timings`."""

    def __init__(self, timings: Timings) -> None:
        self.timings = timings
        self.wall, self.cpu = time.perf_counter(), time.process_time()

    def charge(self, stage: str) -> None:
        wall, cpu = time.perf_counter(), time.process_time()
        self.timings.wall[stage] += wall - self.wall
        self.timings.cpu[stage] += cpu - self.cpu
        self.wall, self.cpu = wall, cpu


@dataclass
class SequenceResult:
    job: Job
    object_ids: list[str]
    # row -> metric -> per-view list (jaccard, fscore_1, fscore_2; below_plane where the scene
    # has a support plane: the share of the predicted voxels whose centre lies below it)
    per_view: dict[str, dict[str, list[float]]]
    # row -> JointError.as_dict() (only for grasped jobs)
    grasps: dict[str, dict] = field(default_factory=dict)
    timings: Timings = field(default_factory=Timings)
    example: dict | None = None  # final-view grids for the figures
    # row (and TRUE_MESH) -> lift test summary (only for physics jobs)
    physics: dict[str, dict] = field(default_factory=dict)
    # fscore_1 / fscore_2 -> per-view F-score of the 40³ target itself (a perfect completion);
    # below_plane -> the target's share below the support plane (scenes with one)
    ceiling: dict[str, list[float]] = field(default_factory=dict)
    elevation_deg: list[float] = field(default_factory=list)  # the camera's, per view
    # the benchmark's object record (grasp.evaluate.benchmark.object_record): "rows": row -> outcome
    benchmark: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------ per-sequence work


def key_seed(*parts: object) -> int:
    """A stable 32-bit seed from the job's identity (same seed → same samples and grasps)."""
    return zlib.crc32("/".join(map(str, parts)).encode())


def truth_mesh_in_latest_camera(seq: Sequence):
    """The true object mesh (single-object sequences) posed in the final view's camera frame."""
    ids = seq.meta["object_ids"]
    if len(ids) != 1:
        raise ValueError(f"the grasp ground truth needs a single-object sequence, got {ids}")
    return object_meshes_in_camera(seq, len(seq) - 1)[0]


def below_plane(occupied: np.ndarray, seq: Sequence, view: int) -> float:
    """The share of ``occupied`` voxels (a 40³ bool grid of view ``view``) whose centre lies
    below the scene's support plane (``meta["support_plane"]``, world frame); 0 when empty."""
    n = int(occupied.sum())
    if n == 0:
        return 0.0
    plane = G.plane_in_frame(seq.meta["support_plane"], seq.camera_to_world[view])
    return int((occupied & G.voxels_below_plane(seq.grid_to_camera[view], plane)).sum()) / n


class Evaluator:
    """Owns what a worker keeps between sequences: a renderer, the loaded models, the rows."""

    def __init__(self, settings: Settings) -> None:
        from completion.render import Renderer

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

    def benchmark_rows(self) -> list[str]:
        """The grasp-benchmark rows this run's models allow (the true mesh always)."""
        from grasp.evaluate.benchmark import BENCHMARK_ROWS, ROW_SOURCES

        def runs(source: str | None) -> bool:
            if source == "fusion":
                return FUSION in self.settings.rows and "mvp" in self.models
            return source is None or source in self.models

        return [r for r in BENCHMARK_ROWS if runs(ROW_SOURCES[r][0])]

    def _benchmark(self, job: Job) -> SequenceResult:
        from grasp.evaluate import benchmark as b

        timings = Timings()
        clock = _StageClock(timings)
        object_id = job.pool[0]
        scene = b.make_scene(object_id, job.index, self.settings.seed, self.renderer)
        seed = key_seed(self.settings.seed, job.table, job.index)
        with quiet_fds(1):
            outcome = b.run_object(scene, self.models, self.benchmark_rows(),
                                   candidates=self.settings.benchmark_candidates, seed=seed)
        clock.charge("benchmark")
        record = b.object_record(object_id, scene.mesh, outcome)
        return SequenceResult(job, [object_id], {}, timings=timings, benchmark=record)

    def evaluate(self, job: Job) -> SequenceResult:
        from completion.scenes import make_sequence
        from grasp import metrics

        if job.table == BENCHMARK_TABLE:
            return self._benchmark(job)
        s = self.settings
        timings = Timings()
        clock = _StageClock(timings)
        seq = make_sequence(
            job.condition,
            job.split,
            job.index,
            s.seed,
            views=s.views,
            pool=list(job.pool) if job.pool is not None else None,
            noise=job.noise,
            renderer=self.renderer,
        )
        clock.charge("generation")
        elevation = list(seq.meta["elevation_deg"])
        if job.table == OVERHEAD_TABLE and max(elevation) < OVERHEAD_MIN_ELEVATION_DEG:
            # searched, no view from above: nothing of it reaches the overhead table
            return SequenceResult(job, list(seq.meta["object_ids"]), {}, timings=timings,
                                  elevation_deg=elevation)
        probs = self.probabilities(seq)
        clock.charge("inference")
        thresholds = {row: self.threshold(row, job.condition) for row in s.rows}
        per_view = {row: {"jaccard": [], "fscore_1": [], "fscore_2": []} for row in s.rows}
        ceiling: dict[str, list[float]] = {"fscore_1": [], "fscore_2": []}
        plane = "support_plane" in seq.meta
        for v in range(len(seq)):
            for row in s.rows:
                occupied = probs[row][v] >= thresholds[row]
                per_view[row]["jaccard"].append(metrics.jaccard(occupied, seq.targets[v]))
                if plane:
                    per_view[row].setdefault("below_plane", []).append(
                        below_plane(occupied, seq, v))
            if plane:  # the target's own share: voxels the surface cuts, centres just below
                ceiling.setdefault("below_plane", []).append(below_plane(seq.targets[v], seq, v))
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
        clock.charge("completion_metrics")
        grasps: dict[str, dict] = {}
        physics: dict[str, dict] = {}
        if job.grasp and not job.light and job.condition in SINGLE_OBJECT_CONDITIONS:
            from grasp.collision import CollisionScene

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
        clock.charge("grasping")
        example = None
        if job.example:

            example = {
                "input": np.packbits(seq.inputs[-1]),
                "target": np.packbits(seq.targets[-1]),
                "grid_to_camera": seq.grid_to_camera[-1],
                "camera_to_world": seq.camera_to_world[-1],
                "object_to_world": seq.meta["object_to_world"][-1],
                "rows": {r: np.packbits(probs[r][-1] >= thresholds[r]) for r in s.rows},
                "probabilities": {r: probs[r][-1] for r in figure_rows(list(grasps))},
                "thresholds": thresholds,
            }
        return SequenceResult(
            job, list(seq.meta["object_ids"]), per_view, grasps, timings, example, physics, ceiling,
            elevation_deg=elevation,
        )

    def _lift_tests(self, job: Job, truth, truth_scene, planned: dict, plan_seed: int) -> dict:
        """row -> lift test of the grasp planned on that row's prediction; TRUE_MESH -> of a
        grasp planned on the true mesh. Every grasp is executed the same way, on the true object
        with a guarded approach (move in until contact), so the true-mesh row differs from the
        model rows only in the shape it was planned on."""
        from grasp.physics import lift_test
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


_WORKER: Evaluator | None = None


def _init_worker(settings: Settings) -> None:
    global _WORKER
    import torch

    torch.set_num_threads(1)
    _WORKER = Evaluator(settings)


def _run_job(job: Job) -> SequenceResult:
    assert _WORKER is not None, "worker not initialised"
    return _WORKER.evaluate(job)


# ------------------------------------------------------------------------------ planning the run


def make_jobs(settings: Settings) -> list[Job]:
    """Every sequence of the run, in a fixed order (results do not depend on the workers)."""
    jobs = []
    for condition in settings.conditions:
        for split in EVAL_SPLITS:
            for index in range(settings.count):
                jobs.append(
                    Job(
                        MAIN_TABLE,
                        condition,
                        split,
                        index,
                        grasp=index < settings.grasp_count,
                        example=split == "test" and index == 0,
                        physics=split == "test"
                        and index < min(settings.grasp_count, settings.physics_count),
                    )
                )
        if condition in SINGLE_OBJECT_CONDITIONS:  # more grasps for the test's joint error
            for index in range(settings.count, settings.grasp_count):
                jobs.append(Job(MAIN_TABLE, condition, "test", index, grasp=True,
                                grasp_only=True, physics=index < settings.physics_count))
    for condition in settings.conditions:  # each condition with and without the sensor model,
        for index in range(settings.sensor):  # the same sequences (the main table has one side)
            for noise in (True, False):
                if noise != (condition in NOISY_BY_DEFAULT) or index >= settings.count:
                    jobs.append(Job(SENSOR_TABLE, condition, "test", index, noise=noise,
                                    light=True))
    if "tabletop" in settings.conditions:  # searched for overhead views
        for index in range(settings.overhead):
            jobs.append(Job(OVERHEAD_TABLE, "tabletop", "test", index, light=True))
    if settings.benchmark:
        from grasp.evaluate.benchmark import benchmark_objects

        for index, object_id in enumerate(benchmark_objects(settings.benchmark, settings.seed)):
            jobs.append(Job(BENCHMARK_TABLE, "tabletop", "test", index, pool=(object_id,)))
    named = object_ids("test", sources=("named",))[: settings.named]
    folder = [(NAMED_OBJECTS_TABLE, object_id) for object_id in named]
    folder += [(FOLDER_TABLE, object_id) for object_id in settings.objects]
    for table in (NAMED_OBJECTS_TABLE, FOLDER_TABLE):
        for index, object_id in enumerate(o for t, o in folder if t == table):
            jobs.append(
                Job(
                    table,
                    OBJECT_TABLE_CONDITION,
                    "test",
                    index,
                    pool=(object_id,),
                    grasp=settings.grasp_count > 0,
                    example=index == 0,
                )
            )
    return jobs


def run_jobs(settings: Settings, jobs: list[Job], *, progress: bool = True) -> list[SequenceResult]:
    """Evaluate every job, in a process pool when ``settings.workers > 1`` (on Ray actors with
    ``settings.ray``); results in job order, so the tables do not depend on how they ran."""
    from tqdm import tqdm

    bar = tqdm(total=len(jobs), desc="evaluate", unit="seq", disable=not progress)
    results: list[SequenceResult] = []
    try:
        if settings.ray:
            from completion.cluster import ray_map

            for result in ray_map(_run_job, jobs, workers=settings.workers,
                                  initializer=_init_worker, initargs=(settings,)):  # fmt: skip
                results.append(result)
                bar.update()
        elif settings.workers <= 1 or len(jobs) <= 1:
            import torch

            threads = torch.get_num_threads()
            _init_worker(settings)
            try:
                for job in jobs:
                    results.append(_run_job(job))
                    bar.update()
            finally:
                torch.set_num_threads(threads)
                if _WORKER is not None:
                    _WORKER.close()
        else:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            # spawn: torch and pybullet do not survive fork with live threads/clients.
            with ProcessPoolExecutor(
                min(settings.workers, len(jobs)),
                mp_context=mp.get_context("spawn"),
                initializer=_init_worker,
                initargs=(settings,),
            ) as pool:
                for result in pool.map(_run_job, jobs, chunksize=1):
                    results.append(result)
                    bar.update()
    finally:
        bar.close()
    return results
