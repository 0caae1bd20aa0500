"""The main table: the paper's Tables I–III (Jaccard, F-score, grasp joint error) over every
condition and split, Table I's precision, the joint error per joint and the lift tests' grasp
success (the cells: :mod:`grasp.evaluate.aggregate`)."""

from __future__ import annotations

from collections.abc import Iterable

from completion.scenes import SINGLE_OBJECT_CONDITIONS
from grasp.evaluate.aggregate import aggregate, fscore_ceiling, pooled_per_joint
from grasp.evaluate.cells import CEILING_LABEL, best, fmt, mean_or_none
from grasp.evaluate.config import (
    CONDITION_LABELS,
    EVAL_SPLITS,
    FSCORE_METRICS,
    GRASP_SUCCESS,
    GRASP_SUCCESS_TITLE,
    JOINT_METRICS,
    MAIN_TABLE,
    METRIC_TITLES,
    METRICS,
    PAPER_ORDER,
    PAPER_TABLES,
    REFERENCE_ROWS,
    ROW_LABELS,
    TABLE_ORDER,
    TRUE_MESH,
    Job,
    Settings,
)
from grasp.evaluate.precision import markdown_precision
from grasp.evaluate.sequence_result import SequenceResult
from grasp.evaluate.tables.base import Table
from hands.barrett import JOINT_NAMES

#: Fewer sequences per cell than this make a run a smoke test: its tables bold nothing.
SMOKE_COUNT = 5


class MainTable(Table):
    name, section = MAIN_TABLE, "main"

    def jobs(self, settings: Settings) -> list[Job]:
        """``count`` sequences per condition and split (the first ``grasp_count`` grasped, the
        test split's first ``physics_count`` of those lift-tested, the first test one drawn in
        the figures), and grasp-only test sequences up to ``grasp_count``."""
        jobs = []
        for condition in settings.conditions:
            for split in EVAL_SPLITS:
                for index in range(settings.count):
                    jobs.append(Job(
                        MAIN_TABLE, condition, split, index,
                        grasp=index < settings.grasp_count,
                        example=split == "test" and index == 0,
                        physics=split == "test"
                        and index < min(settings.grasp_count, settings.physics_count),
                    ))
            if condition in SINGLE_OBJECT_CONDITIONS:  # more grasps for the test's joint error
                for index in range(settings.count, settings.grasp_count):
                    jobs.append(Job(MAIN_TABLE, condition, "test", index, grasp=True,
                                    grasp_only=True, physics=index < settings.physics_count))
        return jobs

    def summarise(self, results: list[SequenceResult], settings: Settings) -> dict:
        main = aggregate(results, settings, MAIN_TABLE)
        return {
            "tables": main["tables"],
            "counts": main["counts"],
            "fscore_ceiling": fscore_ceiling(main["ceiling"]),
            "grasp_success_counts": main["grasp_success_counts"],
            "grasp_failures": main["grasp_failures"],
            "joint_error_per_joint_deg": main["joint_error_per_joint_deg"],
            "pooled_joint_error_per_joint_deg": pooled_per_joint(results, settings),
            "per_view_jaccard": main["per_view_jaccard"],
            "jaccard_precision": main["jaccard_precision"],
            "tabletop_as_served": _as_served(results, settings),
        }

    def parts(self, results: dict, *, bold: bool) -> list[tuple[list[str], str]]:
        """Its lines of results.md in parts, each with the section whose tables follow it:
        Table I and its precision ("jaccard"), the other tables and grasp success ("grasps"),
        the grasps left out ("objects")."""
        # metric -> condition -> split -> F-score of the 40³ target itself
        ceiling = {
            m: {
                c: {s: v[m] for s, v in block["by_split"].items()}
                for c, block in (results.get("fscore_ceiling") or {}).items()
            }
            for m in FSCORE_METRICS
        }
        out: list[tuple[list[str], str]] = []
        parts: list[str] = []
        for metric in METRICS:
            ours = results["tables"][metric]
            counts = results["counts"] if metric in JOINT_METRICS else None
            parts += [
                f"## {METRIC_TITLES[metric]}",
                "",
                markdown_table(ours, metric, counts=counts, ceiling=ceiling.get(metric),
                               bold=bold),
                "",
            ]
            paper_metric = "joint_error_deg" if metric == "joint_error_moving_deg" else metric
            if paper_metric in PAPER_TABLES:
                conditions = [c for c in next(iter(ours.values()), {}) if c in PAPER_ORDER]
                note = (
                    " (8-joint means; × 4/3 gives the 6-joint scale)"
                    if metric == "joint_error_moving_deg"
                    else ""
                )
                parts += [
                    f"The paper's numbers for the same cells (— = N/A in the paper){note}:",
                    "",
                    markdown_table(PAPER_TABLES[paper_metric], paper_metric, conditions=conditions),
                    "",
                ]
            if metric == "jaccard":
                parts += markdown_precision(results)
                out.append((parts, "jaccard"))
                parts = []
        parts += _as_served_markdown(results)
        parts += _pooled(results)
        parts += _grasp_success(results)
        out.append((parts, "grasps"))
        out.append((_left_out(results), "objects"))
        return out

    def markdown(self, results: dict) -> list[str]:
        bold = results["config"]["count"] >= SMOKE_COUNT
        return [line for lines, _ in self.parts(results, bold=bold) for line in lines]


def markdown_table(
    tables: dict,
    metric: str,
    *,
    conditions: Iterable[str] | None = None,
    counts: dict | None = None,
    ceiling: dict | None = None,
    bold: bool = True,
) -> str:
    """One of the paper's tables: rows = models, columns = condition × (train, test); ``bold``:
    the best learned model of each column in bold.

    tables : row -> condition -> split -> value (``results["tables"][metric]``, or
    :data:`PAPER_TABLES` ``[metric]``); conditions default to those of the first row.
    counts : results.json's ``counts`` (joint error) or ``grasp_success_counts`` (grasp success):
    each cell then says how many sequences it averages, e.g. "4.21° (9/10)": 9 comparable grasps
    of 10 grasped sequences. ceiling : condition -> split -> value, printed as a last row.
    """
    rows = list(tables)
    if conditions is None:
        conditions = next(iter(tables.values()), {})
    conditions = [c for c in TABLE_ORDER if c in set(conditions)]
    if metric in (*JOINT_METRICS, GRASP_SUCCESS):
        conditions = [c for c in conditions if c in SINGLE_OBJECT_CONDITIONS]
    header = (
        "| Model | "
        + " | ".join(f"{CONDITION_LABELS[c]} {s}" for c in conditions for s in ("train", "test"))
        + " |"
    )
    lines = [header, "|" + "---|" * (1 + 2 * len(conditions))]
    learned = [r for r in rows if r not in (*REFERENCE_ROWS, TRUE_MESH)]
    for row in rows:
        cells = []
        for c in conditions:
            for split in ("train", "test"):
                v = tables[row].get(c, {}).get(split)
                top = best([tables[r].get(c, {}).get(split) for r in learned], metric)
                text = fmt(v, metric)
                tie = v is not None and top is not None and round(v, 2) == round(top, 2)
                if bold and tie and row in learned and len(learned) > 1:
                    text = f"**{text}**"
                n = (counts or {}).get(row, {}).get(c, {}).get(split)
                if n and metric == GRASP_SUCCESS and n["tested"]:
                    text += f" ({n['held']}/{n['tested']})"
                elif n and metric in JOINT_METRICS and n["grasped"]:
                    text += f" ({n['grasp_ok']}/{n['grasped']})"
                cells.append(text)
        lines.append(f"| {ROW_LABELS[row]} | " + " | ".join(cells) + " |")
    if ceiling:
        cells = [
            fmt(ceiling.get(c, {}).get(split), metric)
            for c in conditions
            for split in ("train", "test")
        ]
        lines.append(f"| {CEILING_LABEL} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _as_served(results: list[SequenceResult], settings: Settings) -> dict | None:
    """Tabletop's Jaccard as the service returns the completion, cut at the table: row -> split
    -> mean over views and sequences (None without tabletop sequences)."""
    mine = [r for r in results if r.job.table == MAIN_TABLE and r.job.condition == "tabletop"
            and not r.job.grasp_only]
    if not mine:
        return None
    return {row: {split: mean_or_none(j for r in mine if r.job.split == split
                                      for j in r.per_view[row].get("jaccard_cut", []))
                  for split in EVAL_SPLITS if any(r.job.split == split for r in mine)}
            for row in settings.rows}


def _as_served_markdown(results: dict) -> list[str]:
    block = results.get("tabletop_as_served")
    if not block:
        return []
    splits = list(next(iter(block.values())))
    lines = ["## Tabletop as the service returns it (cut at the table)", "",
             "Table I's tabletop column scores the completion as the model gives it; the service "
             "cuts it at the table (nothing below the plane), which is what a robot plans on. "
             "Jaccard, mean over views and sequences:", "",
             "| Model | " + " | ".join(splits) + " |", "|---|" + "---|" * len(splits)]
    for row, per_split in block.items():
        lines.append(f"| {ROW_LABELS[row]} | "
                     + " | ".join("—" if per_split[s] is None else f"{per_split[s]:.3f}"
                                  for s in splits) + " |")
    return [*lines, ""]


def _grasp_success(results: dict) -> list[str]:
    """The lift-test table with its counts (empty when nothing was lift-tested)."""
    table = results["tables"].get(GRASP_SUCCESS)
    counts = results.get("grasp_success_counts") or {}
    if not table or not any(
        n["tested"] for per_c in counts.values() for per_s in per_c.values() for n in per_s.values()
    ):
        return []
    cfg = results["config"]
    return [
        f"## {GRASP_SUCCESS_TITLE}",
        "",
        f"The first {cfg['physics_count']} grasped test sequences per condition (the train "
        "split is not lift-tested); each cell gives held/tested. Every row's grasp is executed "
        "the same way on the true object: from the pre-grasp pose the hand moves in until it "
        "touches (guarded move), closes, lifts "
        "10 cm and shakes. Model rows use the grasp planned on their prediction; the true-mesh "
        "row uses the grasp planned on the true mesh: what a perfect completion would get. It "
        "is an upper bound only as far as the planner's ranking predicts the lift test; where "
        "a model row beats it, the ranking preferred a grasp that does not hold.",
        "",
        markdown_table(table, GRASP_SUCCESS, counts=counts, bold=cfg["count"] >= SMOKE_COUNT),
        "",
    ]


def _pooled(results: dict) -> list[str]:
    """The joint error per joint, every grasped sequence pooled."""
    pooled = results.get("pooled_joint_error_per_joint_deg") or {}
    if not any(v is not None for v in pooled.values()):
        return []
    return [
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


def _left_out(results: dict) -> list[str]:
    """The grasped sequences without a comparable grasp, and why."""
    lines = []
    for row, per_cond in results["counts"].items():
        for c, per_split in per_cond.items():
            for s, n in per_split.items():
                if c in SINGLE_OBJECT_CONDITIONS and n["grasped"] and n["grasp_ok"] < n["grasped"]:
                    reasons = "; ".join(results["grasp_failures"][row][c][s])
                    lines.append(
                        f"- {ROW_LABELS[row]}, {CONDITION_LABELS[c]} {s}: "
                        f"{n['grasped'] - n['grasp_ok']} of {n['grasped']} without a "
                        f"comparable grasp ({reasons})"
                    )
    if not lines:
        return []
    return ["Grasps left out of the joint-error means (no prediction surface or no grasp found):",
            "", *lines, ""]


MAIN = MainTable()
