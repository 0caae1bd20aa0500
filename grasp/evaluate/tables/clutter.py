"""The clutter table: a target among neighbours on a table, grasped with the neighbours seen as
obstacles and without, lift-tested with the neighbours standing by (the scenes and the rows:
:mod:`grasp.evaluate.clutter_scenes`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from completion.bullet import quiet_fds
from grasp.evaluate import clutter_scenes as c
from grasp.evaluate.benchmark_scenes import _reason_kind, wilson
from grasp.evaluate.cells import fmt
from grasp.evaluate.config import GRASP_SUCCESS, Job, Settings
from grasp.evaluate.failure_figures import failures_figure
from grasp.evaluate.sequence_result import SequenceResult, StageClock, Timings, key_seed
from grasp.evaluate.tables.base import Option, Table, rows_record
from grasp.evaluate.tables.benchmark import CANDIDATES  # the benchmark's, shared: one option

LABELS = {
    "true_meshes": "True meshes (target and neighbours known)",
    "mvp_4views_obstacles": "MVP, 4 views, the seen neighbours as obstacles",
    "mvp_4views_ignoring": "MVP, 4 views, the neighbours ignored (before)",
}


#: A target among neighbours on a table: one job per scene.
CLUTTER_TABLE = "clutter"
#: ``--clutter N``: the scenes.
SIZE = Option(CLUTTER_TABLE, "scenes of the clutter table: a target among 2-5 neighbours on a "
              "table, planned with the seen neighbours as obstacles and without, lift-tested with "
              "the neighbours", quick=1, default=4, full=50)


class ClutterTable(Table):
    name, section, options, stages = CLUTTER_TABLE, "grasps", (SIZE,), ("clutter",)

    def jobs(self, settings: Settings) -> list[Job]:
        return [Job(CLUTTER_TABLE, "tabletop", "test", index)
                for index in range(SIZE.of(settings))]

    def run(self, evaluator: Any, job: Job) -> SequenceResult:
        s = evaluator.settings
        timings = Timings()
        clock = StageClock(timings)
        scene = c.clutter_scene(job.index, s.seed, evaluator.renderer)
        rows = [r for r in c.CLUTTER_ROWS if r == "true_meshes" or "mvp" in evaluator.models]
        with quiet_fds(1):
            outcome = c.run_scene(scene, evaluator.models, rows,
                                  candidates=CANDIDATES.of(s),
                                  seed=key_seed(s.seed, job.table, job.index))
        clock.charge("clutter")
        record = {"id": scene.target_id, "neighbours": scene.neighbour_ids,
                  "gaps_m": [round(g, 4) for g in scene.gaps_m], "rows": outcome}
        return SequenceResult(job, [scene.target_id, *scene.neighbour_ids], {},
                              timings=timings, record=record)

    def records(self, result: SequenceResult, settings: Settings) -> list[dict]:
        return rows_record(result)

    def summarise(self, results: list[SequenceResult], settings: Settings) -> dict:
        """``clutter`` (row -> success, tested, the 95 % interval, the failures; None without
        scenes) and ``clutter_scenes``, one record per scene."""
        mine = [r.record for r in results if r.job.table == CLUTTER_TABLE]
        if not mine:
            return {"clutter": None, "clutter_scenes": []}
        block = {}
        for row in c.CLUTTER_ROWS:
            outcomes = [m["rows"][row] for m in mine if row in m["rows"]]
            if not outcomes:
                continue
            won = sum(o["success"] for o in outcomes)
            reasons: dict[str, int] = {}
            for o in outcomes:
                if not o["success"]:
                    key = _reason_kind(o["reason"]).split(" (")[0]
                    if key.startswith("held, but"):
                        key = "held, but a neighbour was knocked"
                    elif "would hit an obstacle" in key:  # which finger, how far: one kind
                        key = "no grasp planned: every grasp would touch a neighbour"
                    reasons[key] = reasons.get(key, 0) + 1
            block[row] = {"success": won, "tested": len(outcomes),
                          "held": sum(o["held"] for o in outcomes),
                          "ci95": wilson(won, len(outcomes)),
                          "reasons": dict(sorted(reasons.items(), key=lambda kv: -kv[1]))}
        return {"clutter": block, "clutter_scenes": mine}

    def markdown(self, results: dict) -> list[str]:
        block = results.get("clutter")
        if not block:
            return []
        cfg = results["config"]
        lines = [
            "## Grasp success in clutter (higher is better)",
            "",
            f"{len(results['clutter_scenes'])} scenes: a held-out target in a stable pose on a "
            f"table with {c.NEIGHBOURS[0]}–{c.NEIGHBOURS[1]} other test-split objects around "
            f"it, each {100 * c.GAP_M[0]:.0f}–{100 * c.GAP_M[1]:.0f} cm from it, seen in 4 "
            "depth views with the target's mask (the neighbours occlude it in some); each row's "
            f"top-1 grasp ({cfg['benchmark_candidates']} candidates), executed on the true "
            "target with the true neighbours as dynamic bodies: guarded approach, close, lift, "
            "shake. Success: the target held **and** no neighbour moved more than "
            f"{100 * c.MOVE_LIMIT_M:.0f} cm or tilted more than {c.TILT_LIMIT_DEG:.0f}°. The "
            "true-meshes row is what perfect completions of the target and the neighbours "
            "would get; the last row is the planner that ignores the neighbours.",
            "",
            "| Row | Success | Rate | 95 % interval | Target held | Failures |",
            "|---|---|---|---|---|---|",
        ]
        for row, cell in block.items():
            rate = cell["success"] / cell["tested"] if cell["tested"] else None
            failures = "; ".join(f"{n}× {why}" for why, n in cell["reasons"].items()) or "—"
            lines.append(f"| {LABELS[row]} | {cell['success']}/{cell['tested']} | "
                         f"{fmt(rate, GRASP_SUCCESS)} | {100 * cell['ci95'][0]:.0f}–"
                         f"{100 * cell['ci95'][1]:.0f}% | {cell['held']}/{cell['tested']} | "
                         f"{failures} |")
        return lines + ["", "clutter_failures.png shows the failed grasps of MVP's row with the "
                        "obstacles: the target, its neighbours and the hand where it closed.", ""]

    def figures(self, raw: list[SequenceResult], out: Path, plt: Any, *, seed: int) -> list[Path]:
        """clutter_failures.png: MVP's grasps with the seen obstacles that failed (the target
        dropped or a neighbour knocked), the target and its neighbours on a patch of the table
        and the hand where it closed."""
        def scene(r: SequenceResult):
            _, target, _, neighbours, _, _ = c.scene_objects(r.job.index, seed)
            return [target, *neighbours]

        def title(r: SequenceResult, outcome: dict) -> str:
            shaped = (f", pre-shaped {outcome['preshape_deg']:.0f}°" if outcome["preshape_deg"]
                      else "")
            return f"{r.object_ids[0]} ({outcome['kind']}{shaped}): "

        path = failures_figure(raw, out, plt, CLUTTER_TABLE, "mvp_4views_obstacles", scene,
                               title, "Clutter: MVP's grasps with the seen obstacles that failed "
                               "(hand where it closed)", "clutter_failures.png", key="success")
        return [] if path is None else [path]


TABLE = ClutterTable()
