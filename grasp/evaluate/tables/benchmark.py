"""The grasp-benchmark table: objects resting on a table, grasped from one or four views and
lift-tested (the scenes and the lift tests: :mod:`grasp.evaluate.benchmark_scenes`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from completion.bullet import quiet_fds
from grasp.evaluate import benchmark_scenes as b
from grasp.evaluate.benchmark_records import ObjectRecord, RowSummary
from grasp.evaluate.cells import fmt
from grasp.evaluate.config import FUSION, GRASP_SUCCESS, Job, Settings
from grasp.evaluate.failure_figures import failures_figure
from grasp.evaluate.sequence_result import SequenceResult, StageClock, Timings, key_seed
from grasp.evaluate.tables.base import Option, Table, rows_record
from grasp.physics.verify import DEFAULT_VERIFY

LABELS = {
    "true_mesh": "True mesh (planned on the truth)",
    "mvp_1view": "MVP, 1 view",
    "mvp_4views": "MVP, 4 views, camera poses used",
    "mvp_4views_memory": "MVP, 4 views, poses not used (its memory alone)",
    "single_view_1view": "Single-View, 1 view",
    "registered_fusion_4views": "Registered fusion, 4 views (ref.)",
    "true_mesh_verified": "True mesh, verified",
    "mvp_1view_verified": "MVP, 1 view, verified",
    "mvp_4views_verified": "MVP, 4 views, camera poses used, verified",
}


#: The grasp-success benchmark: one job per object.
BENCHMARK_TABLE = "benchmark"
#: ``--benchmark N``: the objects; ``--verified N``: how many of them get the verified rows;
#: ``--benchmark-verify N``: the grasps those try; ``--benchmark-candidates N``: the planner's
#: candidates (the clutter table's too).
SIZE = Option(BENCHMARK_TABLE, "objects of the grasp-success benchmark: objects on a table, "
              "grasped from 1 or 4 views, lift-tested", quick=1, default=30, full=100, bare=100)
VERIFIED = Option("verified", "of the benchmark's objects, how many also get the verified rows: "
                  "the best grasps lift-tested on the planned mesh before the top one is "
                  "chosen", quick=1, default=10, full=100, follows=BENCHMARK_TABLE)
VERIFY = Option("benchmark_verify", "grasps the verified rows try at most, until one holds in "
                "every trial", default=4, least=1)
CANDIDATES = Option("benchmark_candidates", "planner candidates of the benchmark's and the "
                    "clutter table's grasps, as many as the service plans", default=64, least=1)


class BenchmarkTable(Table):
    name, section = BENCHMARK_TABLE, "grasps"
    options, stages = (SIZE, VERIFIED, VERIFY, CANDIDATES), ("benchmark",)

    def jobs(self, settings: Settings) -> list[Job]:
        count = SIZE.of(settings)
        if not count:
            return []
        return [Job(BENCHMARK_TABLE, "tabletop", "test", index, pool=(object_id,))
                for index, object_id in enumerate(b.benchmark_objects(count, settings.seed))]

    def rows(self, evaluator: Any, job: Job) -> list[str]:
        """The benchmark rows this run's models allow (the true mesh always); the verified rows
        for the first ``--verified`` objects."""
        def runs(row: str) -> bool:
            source = b.ROW_SOURCES[row][0]
            if row in b.VERIFIED_ROWS and job.index >= VERIFIED.of(evaluator.settings):
                return False
            if source == "fusion":
                return FUSION in evaluator.settings.rows and "mvp" in evaluator.models
            if source == b.MEMORY:
                return "mvp" in evaluator.models
            return source is None or source in evaluator.models

        return [r for r in b.BENCHMARK_ROWS if runs(r)]

    def run(self, evaluator: Any, job: Job) -> SequenceResult:
        s = evaluator.settings
        timings = Timings()
        clock = StageClock(timings)
        object_id = job.pool[0]
        scene = b.make_scene(object_id, job.index, s.seed, evaluator.renderer)
        seed = key_seed(s.seed, job.table, job.index)
        with quiet_fds(1):
            outcome = b.run_object(scene, evaluator.models, self.rows(evaluator, job),
                                   candidates=CANDIDATES.of(s), seed=seed,
                                   verify=VERIFY.of(s))
        clock.charge("benchmark")
        record = b.object_record(object_id, scene.mesh, outcome)
        return SequenceResult(job, [object_id], {}, timings=timings, record=record)

    def records(self, result: SequenceResult, settings: Settings) -> list[dict]:
        return rows_record(result)

    def summarise(self, results: list[SequenceResult], settings: Settings) -> dict:
        """``grasp_benchmark`` (:func:`grasp.evaluate.benchmark_scenes.summarise`; None without a
        benchmark) and ``grasp_benchmark_objects``, one record per object."""
        mine = [r for r in results if r.job.table == BENCHMARK_TABLE]
        rows = [row for row in b.BENCHMARK_ROWS if any(row in r.record["rows"] for r in mine)]
        return {"grasp_benchmark": b.summarise([r.record["rows"] for r in mine], rows)
                if mine else None,
                "grasp_benchmark_objects": [r.record for r in mine]}

    def markdown(self, results: dict) -> list[str]:
        """Held/tested with the 95 % interval, the planned-vs-executed joints and the failures."""
        block = results.get("grasp_benchmark")
        if not block:
            return []
        cfg = results["config"]
        lines = [
            "## Grasp success on a table (the benchmark; higher is better)",
            "",
            f"{len(results['grasp_benchmark_objects'])} held-out objects, each resting on a table "
            "in a stable pose, seen by a depth camera with the sensor model at 45–90° of elevation "
            "(one view, or a pan of 4); each row's top-1 grasp, planned with the table as an "
            f"obstacle ({cfg['benchmark_candidates']} candidates), executed on the true object "
            "standing on the table: guarded approach, close, lift 10 cm, shake. The interval is "
            "Wilson's 95 % score interval. The true-mesh row is what a perfect completion would "
            "get.",
            "",
            "| Row | Held | Success | 95 % interval | Planned vs executed joints | Failures |",
            "|---|---|---|---|---|---|",
        ]
        records = [ObjectRecord.from_json(r) for r in results["grasp_benchmark_objects"]]
        for row, cell in ((row, RowSummary.from_json(c)) for row, c in block.items()):
            failures = "; ".join(f"{n}× {reason}" for reason, n in cell.reasons.items()) or "—"
            lines.append(f"| {LABELS[row]} | {cell.held}/{cell.tested} | "
                         f"{fmt(cell.rate, GRASP_SUCCESS)} | {100 * cell.ci95[0]:.0f}–"
                         f"{100 * cell.ci95[1]:.0f}% | {_joint_gap(records, row)} | "
                         f"{failures} |")
        lines += ["", "Planned vs executed joints: the median over objects of the mean absolute "
                  "difference between the finger joints the planner predicted and those the lift "
                  "test's hand ended with (8 joints, degrees).", ""]
        lines += _verification(records, cfg)
        failed = [r for r in records if "true_mesh" in r.rows and not r.rows["true_mesh"].held]
        if failed:
            lines += ["Failures of the true-mesh row (benchmark_failures.png shows them):", "",
                      "| Object | Size (cm) | Mass (kg) | Grasp | Why |", "|---|---|---|---|---|"]
            for r in failed:
                o = r.rows["true_mesh"]
                size = " × ".join(f"{100 * v:.0f}" for v in r.size_m)
                lines.append(f"| {r.id} | {size} | {r.mass_kg:.2f} | {o.kind or '—'} | "
                             f"{o.reason} |")
            lines.append("")
        return lines + _flat(records)

    def figures(self, raw: list[SequenceResult], out: Path, plt: Any, *, seed: int) -> list[Path]:
        """benchmark_failures.png: the true-mesh grasps that failed the lift test, each the
        object on a patch of its table and the hand as planned, with why it failed (objects
        with no grasp planned are listed in results.md instead)."""
        def scene(r: SequenceResult):
            return [b.resting_object(r.object_ids[0], r.job.index, seed)[0]]

        def title(r: SequenceResult, outcome: dict) -> str:
            return f"{r.object_ids[0]} ({r.record['mass_kg']:.2f} kg, {outcome['kind']}): "

        path = failures_figure(raw, out, plt, BENCHMARK_TABLE, "true_mesh", scene, title,
                               "Benchmark: the true-mesh grasps that failed the lift test (hand "
                               "as planned)", "benchmark_failures.png")
        return [] if path is None else [path]


def _flat(records: list[ObjectRecord]) -> list[str]:
    """The objects lower than a table pinch's palm (:func:`grasp.hand.pinch.pinch_height`), planned
    on the true mesh: which held, with which grasp, and why the others did not."""
    from grasp.hand.pinch import pinch_height

    low = [r for r in records if r.size_m[2] < pinch_height() and "true_mesh" in r.rows]
    if not low:
        return []
    held = sum(r.rows["true_mesh"].held for r in low)
    lines = [f"Flat and small objects (lower than {100 * pinch_height():.1f} cm on the table, "
             f"where table pinches are tried), planned on the true mesh: {held} of {len(low)} "
             "held.", "",
             "| Object | Size (cm) | Held | Grasp | Why |", "|---|---|---|---|---|"]
    for r in low:
        o = r.rows["true_mesh"]
        size = " × ".join(f"{100 * v:.1f}" for v in r.size_m)
        lines.append(f"| {r.id} | {size} | {'yes' if o.held else 'no'} | {o.kind or '—'} | "
                     f"{o.reason} |")
    return lines + [""]


def _verification(records: list[ObjectRecord], cfg: dict) -> list[str]:
    """The verified rows: how their top grasps' trials on the planned mesh agree with the
    referee on the true object (a confusion table per row)."""
    rows = [row for row in b.VERIFIED_ROWS if any(row in r.rows for r in records)]
    if not rows:
        return []
    v = DEFAULT_VERIFY
    lines = [
        f"Verified rows: the planner lift-tests its best grasps (at most "
        f"{cfg.get('benchmark_verify', '?')}, in {v.trials} perturbed trials each: mass "
        f"×{v.mass_factor[0]:g}–{v.mass_factor[1]:g}, μ {v.friction[0]:g}–{v.friction[1]:g}, "
        "their own shakes) **on the mesh it planned on** (the completion for the MVP rows), "
        "standing on the table, until one holds in every trial; that one is executed on the "
        "true object. Whether the top grasp's trials held, against the referee:",
        "",
        "| Row | objects | grasps tried (median) | trials held, referee held | trials held, "
        "referee dropped | trials dropped, referee held | trials dropped, referee dropped | "
        "not tried |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        outcomes = [r.rows[row] for r in records if row in r.rows]
        cells = {(True, True): 0, (True, False): 0, (False, True): 0, (False, False): 0}
        untried = 0
        for o in outcomes:
            if o.verification is None or not o.verification.tried:
                untried += 1
                continue
            cells[(o.verification.held == o.verification.trials, o.held)] += 1
        tried = [o.tried for o in outcomes if o.tried is not None]
        median = f"{np.median(tried):.0f}" if tried else "—"
        lines.append(f"| {LABELS[row]} | {len(outcomes)} | {median} | {cells[True, True]} | "
                     f"{cells[True, False]} | {cells[False, True]} | {cells[False, False]} | "
                     f"{untried} |")
    return lines + [""]


def _joint_gap(records: list[ObjectRecord], row: str) -> str:
    """The median over objects of the mean |planned − executed| finger joint (degrees)."""
    gaps = [gap for r in records if row in r.rows
            and (gap := r.rows[row].joint_gap_deg) is not None]
    return f"{np.median(gaps):.1f}°" if gaps else "—"


TABLE = BenchmarkTable()
