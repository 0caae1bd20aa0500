"""results.md: the tables in the paper's layout, the paper's numbers beside them, how to read
them."""

from __future__ import annotations

from collections.abc import Iterable

from completion.scenes import SINGLE_OBJECT_CONDITIONS
from grasp.evaluate.cells import CEILING_LABEL, best, fmt
from grasp.evaluate.config import (
    CONDITION_LABELS,
    FSCORE_METRICS,
    GRASP_SUCCESS,
    GRASP_SUCCESS_TITLE,
    JOINT_METRICS,
    METRIC_TITLES,
    METRICS,
    PAPER_ORDER,
    PAPER_TABLES,
    REFERENCE_ROWS,
    ROW_LABELS,
    TABLE_ORDER,
    TRUE_MESH,
)
from grasp.evaluate.precision import markdown_precision
from grasp.evaluate.records import markdown_timings
from grasp.evaluate.tables import TABLES
from hands.barrett import JOINT_NAMES

#: Fewer sequences per cell than this make a run a smoke test: its tables bold nothing.
SMOKE_COUNT = 5


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


def _markdown_grasp_success(results: dict) -> list[str]:
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


def how_to_read(results: dict) -> list[str]:
    """The "how to read this" section: protocol choices, reference rows, differences, figures."""
    cfg = results["config"]
    return [
        "## How to read this",
        "",
        "- **Protocol (as in the paper).** The paper's five conditions of 12 views, and ours, "
        "tabletop (an object resting on a table in a stable pose, a camera 0.4–1.0 m away at "
        "20–90° of elevation, still, panning or on a short arc, seen through the sensor model); "
        "every grid is 40³ and "
        "fitted to the current view's observed points (slide behind's still camera: to every "
        "point seen so far), in that view's camera frame. Jaccard and "
        "F-score are means over the views of a sequence, then over sequences; the joint error is "
        "on the final view of the single-object conditions: plan on the prediction, re-grasp the "
        "prediction and the true object from the same pre-grasp pose, compare the joints.",
        "- **Prior row (input-free reference).** One fixed shape per condition, the voxel-wise "
        "mean of that condition's training targets thresholded on validation "
        "(`python -m completion.prior`). It never looks at the input: it shows what the grid's "
        "fit alone gives (the fit already says where the object is and how big). A model is "
        "worth what it adds over this row.",
        "- **MVP, memory off (ablation reference).** The shipped MVP run on each view alone, "
        "its memory empty every view. MVP minus Single-View mixes what the memory adds with how "
        "differently the two were trained; MVP minus this row, on the same sequences, is the "
        "memory's part alone (the last table of the precision section).",
        "- **Registered fusion row.** The union of every view's observed voxels so far, carried "
        "into the current grid with the known camera poses: what a calibrated arm gets with no "
        "network. It assumes a static scene, so it smears the moving object of slide behind.",
        "- **Ceiling row (F-score).** The 40³ ground-truth grid itself scored like a prediction "
        "against the true object surfaces (inside the grid): what a perfect completion scores "
        "under this protocol (`fscore_ceiling` in results.json). A perfect completion's Jaccard "
        "is 1 by definition. The ceiling is lowest for the two-object conditions; a likely "
        "cause (not measured) is that the grid, fitted to what the camera saw, cuts the second "
        "object, and the 40³ target is closed at the grid's edge where the object is not.",
        "- **F-score sampling.** The prediction and the true surface are sampled independently "
        "and densely (10 points per voxel face of area, at least 8,192), so two samples of one "
        "surface score F@1% ≥ 0.98: the score measures surfaces, not sampling. d = 1% of the "
        "grid side is 0.4 voxel.",
        "- **Joint error, 8 and 6 joints.** The paper's Table III averages the 8 joints; the "
        "re-grasp keeps the planned spread, so the two spread joints never differ and the 8-joint "
        "mean is 0.75 × the mean over the 6 joints that move (second table). Each cell says "
        "(comparable grasps/grasped sequences); a sequence without a comparable grasp (empty "
        "completion, no grasp found) is counted there and listed below, not averaged in.",
        "- **Train and test columns.** The shipped models were trained on sequences drawn with "
        "seed 1; this run draws seed "
        f"{cfg['seed']}, so the \"train\" columns are unseen sequences of the training objects "
        "and the \"test\" columns unseen objects.",
        "- **Where our setup differs from the paper's.** Objects: procedural shapes and "
        "pybullet_data's random and named meshes, not the paper's YCB/Grasp Database set. "
        "Renderer: pybullet depth, noiseless for the paper's five conditions (the sensor table "
        "puts the sensor model on them). Training: minutes on a 2-core CPU (see "
        "completion/weights/README.md), not the paper's 270k sequences on GPUs. Grasps: our "
        "BarrettHand autograsp in python-fcl and pybullet, not GraspIt!. Compare the paper's "
        "numbers for their trend, not their level.",
        "- **Figures.** `jaccard_per_view.png`: Jaccard against the view index per condition "
        "(test split), one line per row: a model with working memory rises as views add up, "
        "and holds its level in object hiding once the object is covered. `examples.png`: the "
        "final view of one test sequence per condition; each panel shows the grid from the "
        "camera (left) and from the side (right, depth to the right), brighter = nearer. "
        "`grasps.png`: per example, the grasp planned on the completion and the same pre-grasp "
        "re-run on the true object, with the joint error.",
        "",
    ]


def markdown_report(results: dict) -> str:
    cfg = results["config"]
    # metric -> condition -> split -> F-score of the 40³ target itself
    ceiling = {
        m: {
            c: {s: v[m] for s, v in block["by_split"].items()}
            for c, block in (results.get("fscore_ceiling") or {}).items()
        }
        for m in FSCORE_METRICS
    }
    smoke = cfg["count"] < SMOKE_COUNT
    bolding = (
        f"**A smoke test**: fewer than {SMOKE_COUNT} sequences per cell, so the figures say only "
        "that the chain runs; nothing is bolded."
        if smoke else "Bold: best learned model per column; the prior and registered-fusion rows "
        "are references, not models."
    )
    parts = [
        "# Evaluation: Multiple View Performers for Shape Completion",
        "",
        f"Seed {cfg['seed']}, {cfg['count']} sequences per condition and split "
        f"({cfg['views']} views each), grasps on the first {cfg['grasp_count']} of them "
        f"({cfg['candidates']} planner candidates). Values are means over sequences of the mean "
        "over views; the joint error is on the final view of the single-object conditions only "
        f"(— where it does not apply, or where no grasp could be compared). {bolding}",
        "",
        *how_to_read(results),
    ]
    for metric in METRICS:
        ours = results["tables"][metric]
        counts = results["counts"] if metric in JOINT_METRICS else None
        parts += [
            f"## {METRIC_TITLES[metric]}",
            "",
            markdown_table(ours, metric, counts=counts, ceiling=ceiling.get(metric),
                           bold=not smoke),
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
            parts += _section(results, "jaccard")
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
    parts += _section(results, "grasps")
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
    if lines:
        parts += [
            "Grasps left out of the joint-error means (no prediction surface or no grasp found):",
            "",
            *lines,
            "",
        ]
    parts += _section(results, "objects")
    parts += [markdown_timings(results), ""]
    return "\n".join(parts)


def _section(results: dict, section: str) -> list[str]:
    """The lines of every table of :data:`~grasp.evaluate.tables.TABLES` placed in ``section``."""
    return [line for table in TABLES if table.section == section
            for line in table.markdown(results)]
