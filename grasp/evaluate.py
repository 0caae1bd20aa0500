"""``python -m grasp.evaluate``: the paper's evaluation (Tables I–III) in one command.

Scenes are generated on the fly, deterministically from ``--seed`` (:func:`make_sequence` of
every condition × {train, test} split, ``--count`` sequences each), every completion model runs
over each whole sequence (the parallel form, which is causal and equals streaming), and each view
is scored against its ground truth:

- Jaccard on the thresholded 40³ grids and F-score@1% / @2% of the grid side (both shapes meshed
  by marching cubes, 8,192 seeded surface samples each; :mod:`grasp.metrics`), averaged over the
  views of a sequence and then over sequences (Tables I and II);
- grasp joint error on the final view of the single-object conditions (Table III): plan on the
  predicted mesh, re-grasp the *true object mesh* placed in the latest camera frame from the same
  pre-grasp pose (:func:`grasp.metrics.grasp_joint_error`). The paper swaps in "the ground truth
  mesh"; we take the object's own mesh rather than a marching-cubes mesh of the 40³ target so
  that the error measures the completion, not the voxelisation of the ground truth.

Rows: the six models of the paper (single_view, mvp, mvt, lstm, mvp3, mvp6) plus the
``registered_fusion`` reference: the union of every view's observed voxels so far, mapped into
the latest view's grid with the known camera poses (what a user with a calibrated arm would do
without a network; it assumes a static scene, so it smears the sliding object of slide_behind).
Every row is scored wherever the metric applies (the paper leaves Single-View N/A for the
conditions it did not train one on; a single-view model applies to every view of every
condition, so we report it). Cells are null only where a metric does not apply (the joint error
of the two-object conditions) or where no sequence of the cell gave a grasp to compare (an empty
completion has no surface to plan on; ``counts`` and ``grasp_failures`` in results.json say how
many and why).

Besides the main table: the held-out named pybullet_data objects (camera_pan, test only, one
sequence per object) and, with ``--objects DIR``, every OBJ/STL/PLY mesh in a folder.

Outputs in ``--out`` (default ``./evaluation/``): ``results.json``, ``results.md`` (the tables in
the paper's layout), ``jaccard_per_view.png`` (the memory story: Jaccard against view index per
condition and model), ``examples.png`` (final-view input, prediction of every row and ground
truth) and ``grasps.png`` (the planned grasp on the prediction and the re-grasp on the truth).

Cost (see :data:`PRESETS`): with trained models the grasping and the F-score meshes take about
equal shares. The default run evaluates 10 sequences per condition and split and grasps every
single-object one with the planner's 24 principal-axis candidates (about 7.5 minutes on two
cores with the shipped U-Net models); ``--quick`` is a one-minute smoke test; ``--full`` uses
50 sequences per cell and the planner's 64 candidates. Stage timings are printed at the end:
each stage's seconds summed over sequences (so over all worker processes), and the wall time of
the whole run.

Determinism: scenes, surface samples and planner candidates are seeded from ``--seed`` and the
sequence's identity, and every worker runs torch on one thread, so the numbers do not depend on
``--workers``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
import zlib
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from completion import grid as G
from completion.objects import load_object, object_ids, objects_in_folder
from completion.scenes import CONDITIONS, SINGLE_OBJECT_CONDITIONS, VIEWS, Sequence
from hands.barrett import JOINT_NAMES

MODEL_NAMES: tuple[str, ...] = ("single_view", "mvp", "mvt", "lstm", "mvp3", "mvp6")
FUSION = "registered_fusion"
ROWS: tuple[str, ...] = (*MODEL_NAMES, FUSION)
ROW_LABELS = {
    "single_view": "Single-View",
    "mvp": "MVP",
    "mvt": "MVT",
    "lstm": "LSTM",
    "mvp3": "MVP3",
    "mvp6": "MVP6",
    FUSION: "Registered fusion (ref.)",
    "true_mesh": "True mesh (upper bound)",
}
#: The grasp-success row of grasps planned on the true mesh itself (the physics upper bound).
TRUE_MESH = "true_mesh"
#: Column order of the paper's tables.
PAPER_ORDER: tuple[str, ...] = (
    "object_hiding",
    "object_reveal",
    "camera_pan",
    "slide_behind",
    "two_object_pan",
)
CONDITION_LABELS = {
    "object_hiding": "Object Hiding",
    "object_reveal": "Object Reveal",
    "camera_pan": "Camera Pan",
    "slide_behind": "Slide Behind Other",
    "two_object_pan": "Two Object Pan",
}
EVAL_SPLITS: tuple[str, ...] = ("train", "test")
METRICS: tuple[str, ...] = ("jaccard", "fscore_1", "fscore_2", "joint_error_deg")
METRIC_TITLES = {
    "jaccard": "Table I: Jaccard (mean over views; higher is better)",
    "fscore_1": "Table II: F-score@1% (mean over views; higher is better)",
    "fscore_2": "F-score@2% (mean over views; higher is better)",
    "joint_error_deg": "Table III: grasp joint error, degrees (final view; lower is better)",
}
HIGHER_IS_BETTER = {
    "jaccard": True,
    "fscore_1": True,
    "fscore_2": True,
    "joint_error_deg": False,
    "grasp_success": True,
}
#: Lift-test success rate (pybullet dynamics, final view of the single-object conditions).
GRASP_SUCCESS = "grasp_success"
GRASP_SUCCESS_TITLE = (
    "Grasp success: planned on the prediction, lifted and shaken on the true object in pybullet "
    "(final view; higher is better)"
)
#: The condition of the named-object and ``--objects`` tables.
OBJECT_TABLE_CONDITION = "camera_pan"
NAMED_OBJECTS_TABLE = "named"
FOLDER_TABLE = "objects"
MAIN_TABLE = "main"
#: The paper's Tables I–III, (train, test) per condition in PAPER_ORDER; None = N/A there.
_PAPER_ROWS = {
    "jaccard": {
        "single_view": (None, None, (0.91, 0.88), None, (0.90, 0.87)),
        "mvp": ((0.90, 0.87), (0.80, 0.78), (0.96, 0.90), (0.97, 0.95), (0.93, 0.89)),
        "mvt": ((0.90, 0.86), (0.80, 0.78), (0.95, 0.90), (0.97, 0.95), (0.92, 0.88)),
        "lstm": ((0.90, 0.86), (0.80, 0.77), (0.93, 0.90), (0.97, 0.95), (0.92, 0.88)),
        "mvp3": ((0.89, 0.86), (0.78, 0.76), (0.92, 0.90), (0.95, 0.94), (0.91, 0.88)),
        "mvp6": ((0.89, 0.87), (0.79, 0.77), (0.93, 0.90), (0.96, 0.95), (0.92, 0.88)),
    },
    "fscore_1": {
        "single_view": (None, None, (0.90, 0.87), None, (0.90, 0.87)),
        "mvp": ((0.90, 0.86), (0.75, 0.71), (0.95, 0.90), (0.97, 0.95), (0.92, 0.88)),
        "mvt": ((0.90, 0.85), (0.75, 0.71), (0.94, 0.90), (0.97, 0.95), (0.91, 0.87)),
        "lstm": ((0.90, 0.85), (0.75, 0.69), (0.92, 0.90), (0.97, 0.95), (0.92, 0.87)),
        "mvp3": ((0.89, 0.86), (0.72, 0.70), (0.91, 0.88), (0.95, 0.94), (0.91, 0.87)),
        "mvp6": ((0.88, 0.85), (0.74, 0.72), (0.92, 0.90), (0.96, 0.95), (0.91, 0.88)),
    },
    "joint_error_deg": {
        "single_view": (None, None, (4.57, 4.62), None, None),
        "mvp": ((4.10, 4.16), (3.80, 3.94), (3.75, 3.83), None, None),
        "mvt": ((4.14, 4.19), (3.85, 3.98), (3.79, 3.84), None, None),
        "lstm": ((4.15, 4.22), (3.88, 3.97), (3.82, 3.89), None, None),
        "mvp3": ((4.23, 4.28), (4.00, 4.09), (3.98, 4.05), None, None),
        "mvp6": ((4.18, 4.22), (3.94, 3.99), (3.92, 3.98), None, None),
    },
}
PAPER_TABLES: dict = {
    metric: {
        row: {
            c: {"train": None if v is None else v[0], "test": None if v is None else v[1]}
            for c, v in zip(PAPER_ORDER, values, strict=True)
        }
        for row, values in rows.items()
    }
    for metric, rows in _PAPER_ROWS.items()
}
"""The paper's numbers in the layout of results.json's ``tables`` (for side-by-side reports)."""
#: Decision threshold of a checkpoint that does not store one.
DEFAULT_THRESHOLD = 0.5


@dataclass(frozen=True)
class Preset:
    """Sizes of a run: sequences per (condition, split), named objects, planner candidates."""

    count: int
    named: int
    candidates: int
    grasp_count: int  # sequences per (condition, split) that are also grasped
    physics_count: int  # of the grasped ones, how many are also lift-tested in pybullet


#: Sizes per preset, from measured costs on one core (process time): generating a sequence
#: 0.2–0.45 s; running the six models over it 0.2 s; Jaccard + F-score of 12 views × 7 rows
#: 1.7 s; one joint error (collision model of the completion, plan, two re-grasps)
#: ≈ 0.15 s + 0.02 s per planner candidate, × 7 rows per grasped sequence.
#: One pybullet lift test (grasp success) ≈ 0.55 s, × 8 (7 rows + the true mesh) per
#: lift-tested sequence.
PRESETS: dict[str, Preset] = {
    # ≈ 90 core-seconds: a smoke test of the whole chain (about a minute on two cores).
    "quick": Preset(count=2, named=3, candidates=8, grasp_count=2, physics_count=1),
    # ≈ 600 core-seconds, about 5 minutes on two cores: the command with no arguments.
    # 100 sequences (10 per condition and split), all 60 single-object ones grasped with
    # 24 candidates (the planner's 24 principal-axis poses), and the 10 named objects.
    "default": Preset(count=10, named=10, candidates=24, grasp_count=10, physics_count=2),
    # ≈ 4,500 core-seconds (about 40 minutes on two cores; use --workers on a bigger machine):
    # 50 sequences per cell and the planner's full 64 candidates.
    "full": Preset(count=50, named=10, candidates=64, grasp_count=50, physics_count=10),
}


@dataclass(frozen=True)
class Settings:
    """Everything a run depends on (written to results.json as ``config``)."""

    rows: tuple[str, ...] = ROWS
    model_paths: tuple[tuple[str, str], ...] = ()  # (name, checkpoint path) per model row
    conditions: tuple[str, ...] = CONDITIONS
    count: int = PRESETS["default"].count
    grasp_count: int = PRESETS["default"].grasp_count
    physics_count: int = PRESETS["default"].physics_count
    named: int = PRESETS["default"].named
    objects: tuple[str, ...] = ()  # file: ids of --objects DIR
    views: int = VIEWS
    seed: int = 0
    candidates: int = PRESETS["default"].candidates
    samples: int = 8192
    workers: int = 1
    examples: bool = True

    def __post_init__(self) -> None:
        unknown = [r for r in self.rows if r not in ROWS]
        if unknown or not self.rows:
            raise ValueError(f"rows must be a non-empty subset of {ROWS}, got {self.rows}")
        bad = [c for c in self.conditions if c not in CONDITIONS]
        if bad:
            raise ValueError(f"conditions must be among {CONDITIONS}, got {bad}")
        missing = [r for r in self.rows if r != FUSION and r not in dict(self.model_paths)]
        if missing:
            raise ValueError(f"no checkpoint path given for model rows {missing}")
        for name in (
            "count",
            "grasp_count",
            "physics_count",
            "named",
            "candidates",
            "samples",
            "workers",
        ):
            if getattr(self, name) < (1 if name in ("candidates", "samples", "workers") else 0):
                raise ValueError(f"{name} out of range: {getattr(self, name)}")
        if self.views < 2:
            raise ValueError(f"views must be >= 2, got {self.views}")


@dataclass(frozen=True)
class Job:
    """One sequence to evaluate."""

    table: str  # MAIN_TABLE, NAMED_OBJECTS_TABLE or FOLDER_TABLE
    condition: str
    split: str
    index: int
    pool: tuple[str, ...] | None = None  # object ids to draw from (None: the split's library)
    grasp: bool = False
    example: bool = False
    physics: bool = False  # also lift-test the grasps in pybullet (grasped jobs only)


STAGES: tuple[str, ...] = (
    "generation",
    "inference",
    "completion_metrics",
    "grasping",
    "physics",
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
    # row -> metric -> per-view list (jaccard, fscore_1, fscore_2)
    per_view: dict[str, dict[str, list[float]]]
    # row -> JointError.as_dict() (only for grasped jobs)
    grasps: dict[str, dict] = field(default_factory=dict)
    timings: Timings = field(default_factory=Timings)
    example: dict | None = None  # final-view grids for the figures
    # row (and TRUE_MESH) -> lift test summary (only for physics jobs)
    physics: dict[str, dict] = field(default_factory=dict)


# ------------------------------------------------------------------------------ fusion baseline

#: Sub-voxel offsets (in voxels) at which an observed voxel is carried into another grid, so that
#: a coarser source grid leaves no holes in a finer destination grid.
_SUBVOXEL = np.array(
    [[x, y, z] for x in (-0.25, 0.25) for y in (-0.25, 0.25) for z in (-0.25, 0.25)]
)


def registered_fusion(
    inputs: np.ndarray, grid_to_camera: np.ndarray, camera_to_world: np.ndarray
) -> np.ndarray:
    """The known-pose reference: (L, 40, 40, 40) bool, view t = union of views 0…t in grid t.

    inputs : (L, 40, 40, 40) bool observed voxels; grid_to_camera, camera_to_world : (L, 4, 4)
    Each observed voxel (8 sub-voxel points) goes grid s → camera s → world → camera t → grid t.
    """
    inputs = np.asarray(inputs, dtype=bool)
    n = len(inputs)
    if inputs.shape[1:] != G.GRID_SHAPE or grid_to_camera.shape != (n, 4, 4):
        raise ValueError("inputs must be (L, 40, 40, 40) with (L, 4, 4) transforms")
    fused = np.zeros_like(inputs)
    world: list[np.ndarray] = []
    for t in range(n):
        idx = np.argwhere(inputs[t]).astype(np.float64)
        sub = (idx[:, None, :] + _SUBVOXEL[None]).reshape(-1, 3)
        cam = G.indices_to_points(sub, grid_to_camera[t])
        world.append(G.transform_points(cam, camera_to_world[t]))
        seen = np.concatenate(world)
        to_camera_t = np.linalg.inv(camera_to_world[t])
        fused[t] = G.voxelize_points(G.transform_points(seen, to_camera_t), grid_to_camera[t])
    return fused


# ------------------------------------------------------------------------------ per-sequence work


@contextlib.contextmanager
def _quiet_stdout():
    """Silence file descriptor 1 (pybullet's C code prints "argv[0]=" on every connect)."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def _key_seed(*parts: object) -> int:
    """A stable 32-bit seed from the job's identity (same seed → same samples and grasps)."""
    return zlib.crc32("/".join(map(str, parts)).encode())


def truth_mesh_in_latest_camera(seq: Sequence):
    """The true object mesh (single-object sequences) posed in the final view's camera frame."""
    ids = seq.meta["object_ids"]
    if len(ids) != 1:
        raise ValueError(f"the grasp ground truth needs a single-object sequence, got {ids}")
    mesh = load_object(ids[0])
    object_to_world = np.asarray(seq.meta["object_to_world"][-1][0])
    mesh.apply_transform(np.linalg.inv(seq.camera_to_world[-1]) @ object_to_world)
    return mesh


class Evaluator:
    """Owns what a worker keeps between sequences: a renderer and the loaded models."""

    def __init__(self, settings: Settings) -> None:
        import torch

        from completion.model import load_model, read_checkpoint
        from completion.render import Renderer

        self.settings = settings
        with _quiet_stdout():
            self.renderer = Renderer()
        self.models = {}
        self.thresholds: dict[str, float] = {}
        for name, path in settings.model_paths:
            if name not in settings.rows:
                continue
            model = load_model(path).eval()
            # the validation-chosen decision threshold: an attribute of the loaded model, or the
            # checkpoint's "threshold" entry, else 0.5
            threshold = getattr(model, "threshold", None)
            if threshold is None:
                threshold = read_checkpoint(path).get("threshold", DEFAULT_THRESHOLD)
            self.thresholds[name] = float(threshold)
            self.models[name] = model
        self.thresholds[FUSION] = 0.5  # a bool grid: meshed between empty and occupied
        self._torch = torch

    def close(self) -> None:
        self.renderer.close()

    def probabilities(self, seq: Sequence) -> dict[str, np.ndarray]:
        """row -> (L, 40, 40, 40) occupancy probabilities (bool for the fusion reference)."""
        torch = self._torch
        x = torch.from_numpy(seq.inputs[None].astype(np.float32))
        out: dict[str, np.ndarray] = {}
        with torch.no_grad():
            for name in self.settings.rows:
                if name == FUSION:
                    out[name] = registered_fusion(
                        seq.inputs, seq.grid_to_camera, seq.camera_to_world
                    )
                else:
                    out[name] = torch.sigmoid(self.models[name](x))[0].numpy()
        return out

    def evaluate(self, job: Job) -> SequenceResult:
        from completion.scenes import make_sequence
        from grasp import metrics

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
            renderer=self.renderer,
        )
        clock.charge("generation")
        probs = self.probabilities(seq)
        clock.charge("inference")
        per_view = {row: {"jaccard": [], "fscore_1": [], "fscore_2": []} for row in s.rows}
        for v in range(len(seq)):
            seed = _key_seed(s.seed, job.table, job.condition, job.split, job.index, v)
            transform = seq.grid_to_camera[v]
            truth = metrics.grid_surface_sample(
                seq.targets[v], transform, threshold=0.5, count=s.samples, seed=seed
            )
            for row in s.rows:
                p, thr = probs[row][v], self.thresholds[row]
                occ = p >= thr
                scores = metrics.fscore_grids(
                    p,
                    seq.targets[v],
                    transform,
                    threshold=thr,
                    count=s.samples,
                    seed=seed,
                    target_sample=truth,
                )
                per_view[row]["jaccard"].append(metrics.jaccard(occ, seq.targets[v]))
                per_view[row]["fscore_1"].append(scores[0].fscore)
                per_view[row]["fscore_2"].append(scores[1].fscore)
        clock.charge("completion_metrics")
        grasps: dict[str, dict] = {}
        physics: dict[str, dict] = {}
        if job.grasp and job.condition in SINGLE_OBJECT_CONDITIONS:
            from grasp.sim import CollisionScene

            truth = truth_mesh_in_latest_camera(seq)
            truth_mesh = CollisionScene(truth)  # built once, reused
            seed = _key_seed(s.seed, job.table, job.condition, job.split, job.index, "grasp")
            planned = {}
            for row in s.rows:
                mesh = metrics.mesh_or_none(
                    probs[row][-1], seq.grid_to_camera[-1], threshold=self.thresholds[row]
                )
                result = metrics.grasp_joint_error(
                    mesh, truth_mesh, n_candidates=s.candidates, seed=seed
                )
                grasps[row] = result.as_dict()
                planned[row] = result.planned
            clock.charge("grasping")
            if job.physics:
                physics = self._lift_tests(job, truth, truth_mesh, planned, seed)
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
                "rows": {r: np.packbits(probs[r][-1] >= self.thresholds[r]) for r in s.rows},
                "probabilities": {r: probs[r][-1] for r in _figure_rows(list(grasps))},
                "thresholds": dict(self.thresholds),
            }
        return SequenceResult(
            job, list(seq.meta["object_ids"]), per_view, grasps, timings, example, physics
        )

    def _lift_tests(self, job: Job, truth, truth_scene, planned: dict, plan_seed: int) -> dict:
        """row -> lift test of the grasp planned on that row's prediction, executed on the true
        object with a guarded (contact) approach; TRUE_MESH -> a grasp planned on the truth."""
        from grasp.physics import lift_test
        from grasp.planner import plan

        s = self.settings
        seed = _key_seed(s.seed, job.table, job.condition, job.split, job.index, "physics")

        def run(grasp, approach: str) -> dict:
            if grasp is None:
                return {"success": False, "reason": "no grasp planned"}
            with _quiet_stdout():
                r = lift_test(truth, grasp, seed=seed, approach=approach)
            return {
                "success": bool(r.success),
                "reason": r.reason,
                "displacement": round(float(r.displacement), 6),
                "held_s": round(float(r.held_s), 4),
            }

        out = {row: run(planned[row], "contact") for row in s.rows}
        best = plan(truth_scene, n_candidates=s.candidates, seed=plan_seed, top_k=1)
        out[TRUE_MESH] = run(best[0] if best else None, "planned")
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
                        physics=index < min(settings.grasp_count, settings.physics_count),
                    )
                )
    named = object_ids("test", sources=("named",))[: settings.named]
    for index, object_id in enumerate(named):
        jobs.append(
            Job(
                NAMED_OBJECTS_TABLE,
                OBJECT_TABLE_CONDITION,
                "test",
                index,
                pool=(object_id,),
                grasp=settings.grasp_count > 0,
                example=index == 0,
            )
        )
    for index, object_id in enumerate(settings.objects):
        jobs.append(
            Job(
                FOLDER_TABLE,
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
    """Evaluate every job, in a process pool when ``settings.workers > 1``; results in job order."""
    from tqdm import tqdm

    bar = tqdm(total=len(jobs), desc="evaluate", unit="seq", disable=not progress)
    results: list[SequenceResult] = []
    try:
        if settings.workers <= 1 or len(jobs) <= 1:
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


# ------------------------------------------------------------------------------ aggregation


def _mean(values: Iterable[float]) -> float | None:
    vals = [v for v in values if v is not None]
    return round(float(np.mean(vals)), 4) if vals else None


def aggregate(results: list[SequenceResult], settings: Settings, table: str) -> dict:
    """Tables for one set of sequences: metric -> row -> condition -> split -> value (or None).

    Also ``counts`` (sequences and successful grasps per cell), ``grasp_failures`` (reasons) and
    ``per_view`` (Jaccard per view index, mean over sequences).
    """
    mine = [r for r in results if r.job.table == table]
    conditions = sorted({r.job.condition for r in mine}, key=CONDITIONS.index)
    splits = [s for s in EVAL_SPLITS if any(r.job.split == s for r in mine)]
    tables: dict = {m: {} for m in METRICS}
    counts: dict = {}
    per_view: dict = {}
    failures: dict = {}
    per_joint: dict = {}
    for row in settings.rows:
        for m in METRICS:
            tables[m][row] = {}
        counts[row], per_view[row], failures[row], per_joint[row] = {}, {}, {}, {}
        for c in conditions:
            for m in METRICS:
                tables[m][row][c] = {}
            counts[row][c], per_view[row][c], failures[row][c] = {}, {}, {}
            per_joint[row][c] = {}
            for s in splits:
                cell = [r for r in mine if r.job.condition == c and r.job.split == s]
                for m in ("jaccard", "fscore_1", "fscore_2"):
                    tables[m][row][c][s] = _mean(np.mean(r.per_view[row][m]) for r in cell)
                grasped = [r.grasps[row] for r in cell if row in r.grasps]
                ok = [g["error_deg"] for g in grasped if g["error_deg"] is not None]
                applies = c in SINGLE_OBJECT_CONDITIONS
                tables["joint_error_deg"][row][c][s] = _mean(ok) if applies else None
                joints = [g["per_joint_deg"] for g in grasped if g["per_joint_deg"] is not None]
                per_joint[row][c][s] = _by_joint(np.mean(joints, axis=0)) if joints else None
                counts[row][c][s] = {
                    "sequences": len(cell),
                    "grasped": len(grasped),
                    "grasp_ok": len(ok),
                }
                failures[row][c][s] = sorted({g["reason"] for g in grasped if g["reason"]})
                per_view[row][c][s] = (
                    [
                        round(float(v), 4)
                        for v in np.mean([r.per_view[row]["jaccard"] for r in cell], axis=0)
                    ]
                    if cell
                    else []
                )
    success: dict = {}
    success_counts: dict = {}
    for row in (*settings.rows, TRUE_MESH):
        success[row], success_counts[row] = {}, {}
        for c in conditions:
            success[row][c], success_counts[row][c] = {}, {}
            for s in splits:
                tested = [
                    r.physics[row]
                    for r in mine
                    if r.job.condition == c and r.job.split == s and row in r.physics
                ]
                held = sum(t["success"] for t in tested)
                applies = c in SINGLE_OBJECT_CONDITIONS and tested
                success[row][c][s] = round(held / len(tested), 4) if applies else None
                success_counts[row][c][s] = {"tested": len(tested), "held": held}
    tables[GRASP_SUCCESS] = success
    return {
        "tables": tables,
        "counts": counts,
        "grasp_success_counts": success_counts,
        "per_view_jaccard": per_view,
        "grasp_failures": failures,
        "joint_error_per_joint_deg": per_joint,
        "conditions": conditions,
        "splits": splits,
    }


def per_object_records(results: list[SequenceResult], settings: Settings) -> list[dict]:
    records = []
    for r in results:
        for row in settings.rows:
            g = r.grasps.get(row)
            records.append(
                {
                    "table": r.job.table,
                    "condition": r.job.condition,
                    "split": r.job.split,
                    "index": r.job.index,
                    "object_ids": r.object_ids,
                    "model": row,
                    "jaccard": _mean(r.per_view[row]["jaccard"]),
                    "fscore_1": _mean(r.per_view[row]["fscore_1"]),
                    "fscore_2": _mean(r.per_view[row]["fscore_2"]),
                    "jaccard_per_view": [round(v, 4) for v in r.per_view[row]["jaccard"]],
                    "joint_error_deg": None if g is None else g["error_deg"],
                    "joint_error_per_joint_deg": None if g is None else g["per_joint_deg"],
                    "grasp": g,
                }
            )
    return records


def _by_joint(values: np.ndarray) -> dict[str, float]:
    return dict(zip(JOINT_NAMES, np.round(values, 4).tolist(), strict=True))


def _pooled_per_joint(results: list[SequenceResult], settings: Settings) -> dict:
    """row -> joint -> mean |Δθ| over every grasped main-table sequence (both splits)."""
    out = {}
    for row in settings.rows:
        joints = [
            r.grasps[row]["per_joint_deg"]
            for r in results
            if r.job.table == MAIN_TABLE
            and row in r.grasps
            and r.grasps[row]["per_joint_deg"] is not None
        ]
        out[row] = _by_joint(np.mean(joints, axis=0)) if joints else None
    return out


def build_results(results: list[SequenceResult], settings: Settings, wall: dict) -> dict:
    timings = Timings()
    for r in results:
        timings.add(r.timings)
    main = aggregate(results, settings, MAIN_TABLE)
    out = {
        "tables": main["tables"],
        "counts": main["counts"],
        "grasp_success_counts": main["grasp_success_counts"],
        "grasp_failures": main["grasp_failures"],
        "joint_error_per_joint_deg": main["joint_error_per_joint_deg"],
        "pooled_joint_error_per_joint_deg": _pooled_per_joint(results, settings),
        "per_view_jaccard": main["per_view_jaccard"],
        "named_objects": None,
        "objects_dir": None,
        "per_object": per_object_records(results, settings),
        "config": _config_dict(settings),
        "paper_tables": PAPER_TABLES,
        "timings_s": {
            "stages_wall_summed_over_sequences": {k: round(v, 2) for k, v in timings.wall.items()},
            "stages_cpu_summed_over_sequences": {k: round(v, 2) for k, v in timings.cpu.items()},
            "wall": {k: round(v, 2) for k, v in wall.items()},
        },
    }
    for table, key in ((NAMED_OBJECTS_TABLE, "named_objects"), (FOLDER_TABLE, "objects_dir")):
        if any(r.job.table == table for r in results):
            agg = aggregate(results, settings, table)
            c = OBJECT_TABLE_CONDITION
            out[key] = {
                "condition": c,
                "split": "test",
                "tables": {
                    m: {row: agg["tables"][m][row][c]["test"] for row in settings.rows}
                    for m in METRICS
                },
                "counts": {row: agg["counts"][row][c]["test"] for row in settings.rows},
                "grasp_failures": {
                    row: agg["grasp_failures"][row][c]["test"] for row in settings.rows
                },
                "objects": [r.object_ids[0] for r in results if r.job.table == table],
            }
    return out


def _config_dict(settings: Settings) -> dict:
    d = asdict(settings)
    d["model_paths"] = dict(settings.model_paths)
    d["objects"] = list(settings.objects)
    d["fscore_fractions"] = [0.01, 0.02]
    d["splits"] = list(EVAL_SPLITS)
    return d


# ------------------------------------------------------------------------------ reporting


def _fmt(value: float | None, metric: str) -> str:
    if value is None:
        return "—"
    if metric == GRASP_SUCCESS:
        return f"{100 * value:.0f}%"
    return f"{value:.2f}°" if metric == "joint_error_deg" else f"{value:.2f}"


def _best(values: list[float | None], metric: str) -> float | None:
    vals = [v for v in values if v is not None]
    if not vals:
        return None
    return max(vals) if HIGHER_IS_BETTER[metric] else min(vals)


def markdown_table(tables: dict, metric: str, *, conditions: Iterable[str] | None = None) -> str:
    """One of the paper's tables: rows = models, columns = condition × (train, test).

    tables : row -> condition -> split -> value (``results["tables"][metric]``, or
    :data:`PAPER_TABLES` ``[metric]``); conditions default to those of the first row.
    """
    rows = list(tables)
    if conditions is None:
        conditions = next(iter(tables.values()), {})
    conditions = [c for c in PAPER_ORDER if c in set(conditions)]
    if metric in ("joint_error_deg", GRASP_SUCCESS):
        conditions = [c for c in conditions if c in SINGLE_OBJECT_CONDITIONS]
    header = (
        "| Model | "
        + " | ".join(f"{CONDITION_LABELS[c]} {s}" for c in conditions for s in ("train", "test"))
        + " |"
    )
    lines = [header, "|" + "---|" * (1 + 2 * len(conditions))]
    learned = [r for r in rows if r not in (FUSION, TRUE_MESH)]
    for row in rows:
        cells = []
        for c in conditions:
            for split in ("train", "test"):
                v = tables[row].get(c, {}).get(split)
                best = _best([tables[r].get(c, {}).get(split) for r in learned], metric)
                text = _fmt(v, metric)
                tie = v is not None and best is not None and round(v, 2) == round(best, 2)
                if tie and row in learned and len(learned) > 1:
                    text = f"**{text}**"
                cells.append(text)
        lines.append(f"| {ROW_LABELS[row]} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def markdown_object_table(block: dict) -> str:
    """Rows = models, columns = the four metrics (camera_pan, test objects only)."""
    tables = block["tables"]
    rows = list(tables["jaccard"])
    lines = [
        "| Model | Jaccard | F@1% | F@2% | Joint error | grasps ok |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        n = block["counts"][row]
        cells = [_fmt(tables[m][row], m) for m in METRICS]
        lines.append(
            f"| {ROW_LABELS[row]} | " + " | ".join(cells) + f" | {n['grasp_ok']}/{n['grasped']} |"
        )
    notes = [
        f"- {ROW_LABELS[row]}: {'; '.join(reasons)}"
        for row, reasons in block["grasp_failures"].items()
        if reasons
    ]
    if notes:
        lines += ["", "Grasps without a comparable result:", "", *notes]
    return "\n".join(lines)


def markdown_timings(results: dict) -> str:
    """Per-stage seconds (wall and CPU, summed over sequences) and the run's wall times."""
    t = results["timings_s"]
    wall, cpu = t["stages_wall_summed_over_sequences"], t["stages_cpu_summed_over_sequences"]
    workers = results["config"]["workers"]
    lines = [
        f"## Timings (seconds; {workers} worker process{'es' if workers > 1 else ''})",
        "",
        "| stage | wall, summed over sequences | CPU, summed over sequences |",
        "|---|---|---|",
        *[f"| {k} | {wall[k]:.1f} | {cpu[k]:.1f} |" for k in wall],
        f"| all stages | {sum(wall.values()):.1f} | {sum(cpu.values()):.1f} |",
        "",
        "| run | wall |",
        "|---|---|",
        *[f"| {k} | {v:.1f} |" for k, v in t["wall"].items()],
    ]
    return "\n".join(lines)


def _markdown_grasp_success(results: dict) -> list[str]:
    """The lift-test table with its counts (empty when nothing was lift-tested)."""
    table = results["tables"].get(GRASP_SUCCESS)
    counts = results.get("grasp_success_counts") or {}
    if not table or not any(
        n["tested"] for per_c in counts.values() for per_s in per_c.values() for n in per_s.values()
    ):
        return []
    lines = []
    for row, per_c in counts.items():
        cells = [
            f"{CONDITION_LABELS[c]} {s} {n['held']}/{n['tested']}"
            for c, per_s in per_c.items()
            if c in SINGLE_OBJECT_CONDITIONS
            for s, n in per_s.items()
            if n["tested"]
        ]
        lines.append(f"- {ROW_LABELS[row]}: " + ", ".join(cells))
    cfg = results["config"]
    return [
        f"## {GRASP_SUCCESS_TITLE}",
        "",
        f"The first {cfg['physics_count']} grasped sequences per condition and split. Model rows: "
        "the grasp planned on the prediction, approached on the true object until contact "
        "(guarded move), closed, lifted 10 cm and shaken. True mesh (upper bound): the grasp "
        "planned on the true mesh, executed as planned.",
        "",
        markdown_table(table, GRASP_SUCCESS),
        "",
        "Lift tests held / run:",
        "",
        *lines,
        "",
    ]


def markdown_report(results: dict) -> str:
    cfg = results["config"]
    parts = [
        "# Evaluation: Multiple View Performers for Shape Completion",
        "",
        f"Seed {cfg['seed']}, {cfg['count']} sequences per condition and split "
        f"({cfg['views']} views each), grasps on the first {cfg['grasp_count']} of them "
        f"({cfg['candidates']} planner candidates). Values are means over sequences of the mean "
        "over views; the joint error is on the final view of the single-object conditions only "
        "(— where it does not apply, or where no grasp could be compared). Bold: best learned "
        "model per column. The registered-fusion row is a reference with known camera poses, "
        "not a model of the paper.",
        "",
    ]
    for metric in METRICS:
        ours = results["tables"][metric]
        parts += [f"## {METRIC_TITLES[metric]}", "", markdown_table(ours, metric), ""]
        if metric in PAPER_TABLES:
            conditions = next(iter(ours.values()), {})
            parts += [
                "The paper's numbers for the same cells (— = N/A in the paper):",
                "",
                markdown_table(PAPER_TABLES[metric], metric, conditions=conditions),
                "",
            ]
    pooled = results.get("pooled_joint_error_per_joint_deg") or {}
    if any(v is not None for v in pooled.values()):
        parts += [
            "Joint error per joint, degrees (every grasped sequence of the table above, pooled):",
            "",
            "| Model | " + " | ".join(JOINT_NAMES) + " |",
            "|---|" + "---|" * len(JOINT_NAMES),
            *[
                f"| {ROW_LABELS[row]} | "
                + " | ".join("—" if v is None else f"{v[j]:.2f}" for j in JOINT_NAMES)
                + " |"
                for row, v in pooled.items()
            ],
            "",
        ]
    parts += _markdown_grasp_success(results)
    counts = results["counts"]
    lines = []
    for row, per_cond in counts.items():
        for c, per_split in per_cond.items():
            for s, n in per_split.items():
                if c in SINGLE_OBJECT_CONDITIONS and n["grasped"] and n["grasp_ok"] < n["grasped"]:
                    reasons = "; ".join(results["grasp_failures"][row][c][s])
                    lines.append(
                        f"- {ROW_LABELS[row]}, {CONDITION_LABELS[c]} {s}: "
                        f"{n['grasped'] - n['grasp_ok']} of {n['grasped']} without a "
                        f"comparable grasp ({reasons})"
                    )
    if lines:
        parts += [
            "Grasps left out of Table III (no prediction surface or no grasp found):",
            "",
            *lines,
            "",
        ]
    for key, title in (
        ("named_objects", "Held-out named pybullet_data objects"),
        ("objects_dir", "Objects from --objects"),
    ):
        block = results.get(key)
        if block:
            parts += [
                f"## {title} (camera pan, test)",
                "",
                f"Objects: {', '.join(block['objects'])}",
                "",
                markdown_object_table(block),
                "",
            ]
    parts += [
        "Notes: F-score samples 8,192 points on each marching-cubes surface (same seed for "
        "both sides); resampling the very same surface already costs a few points of "
        "F@1% (d is 0.4 voxel), so F@1% is below 1 even for a perfect completion. An "
        "empty prediction scores F = 0. Single-View is scored on every condition (the "
        "paper leaves some cells N/A). The grasp ground truth is the object's own mesh in the "
        "final camera frame; prediction and truth are both grasped from the planned grasp's "
        "pre-grasp pose (backed off 0.2 m, hand open, same spread).",
        "",
        markdown_timings(results),
        "",
    ]
    return "\n".join(parts)


# ------------------------------------------------------------------------------ figures


def _unpack(bits: np.ndarray) -> np.ndarray:
    return np.unpackbits(bits)[: G.GRID_SIZE**3].astype(bool).reshape(G.GRID_SHAPE)


def _projections(occupancy: np.ndarray) -> np.ndarray:
    """(40, 81) float image, NaN where empty: the grid seen from the camera and from its side.

    Left: along the camera's +z (rows = y, columns = x), brightness = nearness of the first
    occupied voxel. Right: along +x (rows = y, columns = z, depth to the right), brightness =
    nearness to that side. Shows how far behind the visible surface a completion reaches.
    """
    n = G.GRID_SIZE
    depth = np.arange(n, dtype=np.float64)

    def first_hit(occ: np.ndarray) -> np.ndarray:  # occ (rows, cols, depth)
        hit = occ.any(axis=-1)
        first = np.where(hit, np.argmax(occ, axis=-1), 0)
        return np.where(hit, 1.0 - depth[first] / n, np.nan)

    front = first_hit(occupancy.transpose(1, 0, 2))  # (y, x) along z
    side = first_hit(occupancy.transpose(1, 2, 0))  # (y, z) along x
    return np.concatenate([front, np.full((n, 1), np.nan), side], axis=1)


def write_figures(results: dict, raw: list[SequenceResult], out: Path) -> list[Path]:
    """jaccard_per_view.png, examples.png and grasps.png (when there are grasps)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    written = []
    per_view = results["per_view_jaccard"]
    rows = list(per_view)
    conditions = [c for c in PAPER_ORDER if c in next(iter(per_view.values()), {})]
    if conditions:
        fig, axes = plt.subplots(
            1, len(conditions), figsize=(3.6 * len(conditions), 3.4), squeeze=False, sharey=True
        )
        for ax, c in zip(axes[0], conditions, strict=True):
            for row in rows:
                split = "test" if per_view[row][c].get("test") else "train"
                ys = per_view[row][c].get(split) or []
                style = "--" if row == FUSION else "-"
                ax.plot(range(1, len(ys) + 1), ys, style, marker=".", label=ROW_LABELS[row])
            ax.set_title(CONDITION_LABELS[c])
            ax.set_xlabel("view")
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            ax.grid(alpha=0.3)
        axes[0][0].set_ylabel("Jaccard (test)")
        axes[0][-1].legend(fontsize=7, loc="lower right")
        fig.tight_layout()
        path = out / "jaccard_per_view.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)

    examples = [r for r in raw if r.example is not None]
    if examples:
        row_names = list(examples[0].example["rows"])
        cols = ["input", "ground truth", *row_names]
        fig, axes = plt.subplots(
            len(examples),
            len(cols),
            figsize=(1.9 * len(cols), 1.2 * len(examples) + 0.6),
            squeeze=False,
        )
        for i, r in enumerate(examples):
            ex = r.example
            grids = [
                _unpack(ex["input"]),
                _unpack(ex["target"]),
                *[_unpack(ex["rows"][n]) for n in row_names],
            ]
            for j, (title, occ) in enumerate(zip(cols, grids, strict=True)):
                ax = axes[i][j]
                ax.imshow(_projections(occ), cmap="viridis", vmin=0.0, vmax=1.0)
                ax.set_xticks([])
                ax.set_yticks([])
                if i == 0:
                    ax.set_title(ROW_LABELS.get(title, title), fontsize=8)
                if j == 0:
                    ax.set_ylabel(f"{r.job.table}\n{CONDITION_LABELS[r.job.condition]}", fontsize=7)
        fig.suptitle(
            "Final view of each example: front (as the camera sees it) | side (depth to the "
            "right); brighter = nearer",
            fontsize=8,
        )
        fig.tight_layout()
        path = out / "examples.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)

    path = _grasp_figure(raw, out, plt)
    if path is not None:
        written.append(path)
    return written


#: Rows shown in grasps.png (the first ones present): the paper's model, a baseline, the reference.
GRASP_FIGURE_ROWS: tuple[str, ...] = ("mvp", "single_view", FUSION)
#: Examples shown in grasps.png (main table first: camera pan, hiding, reveal).
GRASP_FIGURE_EXAMPLES = 3


def _figure_rows(rows: list[str]) -> list[str]:
    return [n for n in GRASP_FIGURE_ROWS if n in rows] or rows[:1]


def _grasp_result(summary: dict):
    """A ``GraspResult`` carrying the pose and joints of a JSON grasp summary (for rendering)."""
    from grasp.autograsp import GraspResult, HandDofs, HandJoints

    joints = HandJoints(*summary["joints_deg"])
    return GraspResult(
        summary["success"],
        summary["reason"],
        np.asarray(summary["palm_pose"]),
        joints,
        HandDofs(summary["spread_deg"], 0.0, 0.0, 0.0),
    )


def _grasp_figure(raw: list[SequenceResult], out: Path, plt) -> Path | None:
    """grasps.png: per example, the grasp on the prediction and the re-grasp on the truth.

    Rendered with :func:`grasp.render.render_grasp` (pybullet TinyRenderer, side view).
    """
    from grasp import metrics
    from grasp.render import render_grasp

    shown = [r for r in raw if r.example is not None and r.grasps][:GRASP_FIGURE_EXAMPLES]
    if not shown:
        return None
    rows = _figure_rows(list(shown[0].grasps))
    cols = [(n, side) for n in rows for side in ("on_prediction", "on_truth")]
    fig, axes = plt.subplots(
        len(shown), len(cols), figsize=(2.4 * len(cols), 2.6 * len(shown)), squeeze=False
    )
    for i, r in enumerate(shown):
        ex = r.example
        seq_like = Sequence(
            np.zeros((1, *G.GRID_SHAPE), bool),
            np.zeros((1, *G.GRID_SHAPE), bool),
            ex["grid_to_camera"][None],
            ex["camera_to_world"][None],
            {"object_ids": r.object_ids, "object_to_world": [ex["object_to_world"]]},
        )
        truth = truth_mesh_in_latest_camera(seq_like)
        for j, (name, side) in enumerate(cols):
            ax = axes[i][j]
            ax.axis("off")
            g = r.grasps[name]
            title = f"{ROW_LABELS[name]}: " + ("prediction" if side == "on_prediction" else "truth")
            if j == 0:
                title = f"{r.job.table} {CONDITION_LABELS[r.job.condition]}\n" + title
            if side == "on_truth" and g["error_deg"] is not None:
                title += f" ({g['error_deg']:.1f}°)"
            ax.set_title(title, fontsize=7)
            if g[side] is None:
                ax.text(0.5, 0.5, g["reason"], ha="center", va="center", fontsize=6, wrap=True)
                continue
            mesh = truth
            if side == "on_prediction":
                mesh = metrics.mesh_or_none(
                    ex["probabilities"][name],
                    ex["grid_to_camera"],
                    threshold=ex["thresholds"][name],
                )
            with _quiet_stdout():
                image = render_grasp(mesh, _grasp_result(g[side]), width=240, height=240)[0]
            ax.imshow(image)
    fig.suptitle(
        "Grasp planned on the completion, and the same pre-grasp re-run on the truth", fontsize=9
    )
    fig.tight_layout()
    path = out / "grasps.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


# ------------------------------------------------------------------------------ command line


def evaluate(settings: Settings, *, out: Path | None = None, progress: bool = True) -> dict:
    """Run the whole evaluation; write results.json, results.md and figures when ``out``."""
    t0 = time.perf_counter()
    jobs = make_jobs(settings)
    raw = run_jobs(settings, jobs, progress=progress)
    t1 = time.perf_counter()
    wall = {"sequences": t1 - t0}
    results = build_results(raw, settings, wall)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        t2 = time.perf_counter()
        if settings.examples:
            write_figures(results, raw, out)
        results["timings_s"]["wall"]["figures"] = round(time.perf_counter() - t2, 2)
        results["timings_s"]["wall"]["total"] = round(time.perf_counter() - t0, 2)
        (out / "results.json").write_text(json.dumps(results, indent=1))
        (out / "results.md").write_text(markdown_report(results))
    else:
        results["timings_s"]["wall"]["total"] = round(time.perf_counter() - t0, 2)
    return results


def _list_arg(choices: tuple[str, ...], what: str):
    """Comma list of names, in any case and with the tables' spelling too ("MVP", "Single-View",
    "Camera Pan" mean mvp, single_view, camera_pan)."""

    def parse(text: str) -> tuple[str, ...]:
        items = tuple(
            "_".join(x.strip().lower().replace("-", " ").split())
            for x in text.split(",")
            if x.strip()
        )
        if text.strip() == "all":
            return choices
        bad = [x for x in items if x not in choices]
        if bad or not items:
            raise argparse.ArgumentTypeError(
                f"expected a comma-separated list of {what} from {', '.join(choices)} (or 'all'), "
                f"got {text!r}"
            )
        return tuple(dict.fromkeys(items))

    return parse


def _positive(minimum: int):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {value}")
        return value

    return parse


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m grasp.evaluate",
        description="The paper's evaluation: Jaccard, F-score@1%/2% and grasp joint error for "
        "every model on freshly generated scenes (deterministic from --seed).",
    )
    size = p.add_mutually_exclusive_group()
    size.add_argument(
        "--quick",
        action="store_const",
        const="quick",
        dest="preset",
        help="a smoke test of the whole chain (about a minute on two free cores)",
    )
    size.add_argument(
        "--full",
        action="store_const",
        const="full",
        dest="preset",
        help="50 sequences per cell, the planner's 64 candidates (about 40 min on two cores)",
    )
    p.set_defaults(preset="default")
    p.add_argument(
        "--conditions",
        type=_list_arg(CONDITIONS, "conditions"),
        default=CONDITIONS,
        help="comma-separated conditions (default: all five)",
    )
    p.add_argument(
        "--models",
        type=_list_arg(ROWS, "rows"),
        default=ROWS,
        help=f"comma-separated rows (default: all of {', '.join(ROWS)})",
    )
    p.add_argument(
        "--objects",
        type=Path,
        default=None,
        metavar="DIR",
        help="also evaluate every OBJ/STL/PLY mesh in DIR (camera pan, one sequence each)",
    )
    p.add_argument(
        "--count",
        type=_positive(1),
        default=None,
        help="sequences per condition and split (overrides the preset)",
    )
    p.add_argument(
        "--grasp-count",
        type=_positive(0),
        default=None,
        help="of those, how many are also grasped (single-object conditions)",
    )
    p.add_argument(
        "--physics-count",
        type=_positive(0),
        default=None,
        metavar="N",
        help="of the grasped sequences, how many are also lift-tested in pybullet dynamics "
        "(grasp success; 0 = none; default: 2, 1 with --quick, 10 with --full)",
    )
    p.add_argument(
        "--named",
        type=_positive(0),
        default=None,
        help="held-out named pybullet_data objects to evaluate (0 = none)",
    )
    p.add_argument(
        "--candidates",
        type=_positive(1),
        default=None,
        help="grasp planner candidates per plan (overrides the preset)",
    )
    p.add_argument("--views", type=_positive(2), default=VIEWS, help="views per sequence")
    p.add_argument(
        "--workers",
        type=_positive(1),
        default=None,
        help="worker processes (default: the CPUs this process may use)",
    )
    p.add_argument("--seed", type=int, default=0, help="one seed for scenes, samples and grasps")
    p.add_argument(
        "--weights",
        type=Path,
        default=None,
        metavar="DIR",
        help="folder of <model>.pt checkpoints (default: completion/weights/)",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=Path("evaluation"),
        metavar="DIR",
        help="where results.json, results.md and the figures go (default: evaluation/)",
    )
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def settings_from_args(args: argparse.Namespace, parser: argparse.ArgumentParser) -> Settings:
    from completion.model import WEIGHTS_DIR

    preset = PRESETS[args.preset]
    weights = args.weights if args.weights is not None else WEIGHTS_DIR
    paths = []
    for name in args.models:
        if name == FUSION:
            continue
        path = Path(weights) / f"{name}.pt"
        if not path.is_file():
            train = f"python -m completion.train --model {name} --out {path}"
            if name in ("mvp3", "mvp6"):
                train = f"python -m completion.train --model {name} --views {name[-1]} --out {path}"
            parser.exit(
                2,
                f"{parser.prog}: error: missing weights for model {name!r}: {path} "
                f"does not exist. Train them with `{train}` (see "
                "completion/weights/README.md), pass --weights DIR, or leave the "
                f"model out with --models.\n",
            )
        paths.append((name, str(path)))
    objects: tuple[str, ...] = ()
    if args.objects is not None:
        try:
            objects = tuple(objects_in_folder(args.objects))
            for object_id in objects:
                load_object(object_id)  # unreadable meshes fail here, not in a worker
        except ValueError as exc:
            parser.error(f"--objects: {exc}")
    workers = args.workers
    if workers is None:
        workers = (
            len(os.sched_getaffinity(0))
            if hasattr(os, "sched_getaffinity")
            else (os.cpu_count() or 1)
        )
    count = args.count if args.count is not None else preset.count
    return Settings(
        rows=tuple(args.models),
        model_paths=tuple(paths),
        conditions=tuple(args.conditions),
        count=count,
        grasp_count=min(
            count, args.grasp_count if args.grasp_count is not None else preset.grasp_count
        ),
        physics_count=args.physics_count
        if args.physics_count is not None
        else preset.physics_count,
        named=args.named if args.named is not None else preset.named,
        objects=objects,
        views=args.views,
        seed=args.seed,
        candidates=args.candidates if args.candidates is not None else preset.candidates,
        workers=workers,
        examples=not args.no_figures,
    )


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    settings = settings_from_args(args, parser)
    results = evaluate(settings, out=args.out, progress=not args.quiet)
    print(markdown_report(results))
    print(f"wrote {args.out / 'results.json'}, {args.out / 'results.md'} and figures")
    return 0


if __name__ == "__main__":
    sys.exit(main())


__all__ = [
    "Evaluator",
    "Job",
    "Settings",
    "PRESETS",
    "ROWS",
    "MODEL_NAMES",
    "FUSION",
    "aggregate",
    "build_results",
    "evaluate",
    "make_jobs",
    "markdown_report",
    "registered_fusion",
    "run_jobs",
]
