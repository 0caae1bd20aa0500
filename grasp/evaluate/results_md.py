"""results.md: the tables in the paper's layout, the paper's numbers beside them, how to read
them."""

from __future__ import annotations

from grasp.evaluate.tables import TABLES
from grasp.evaluate.tables.main import MAIN, SMOKE_COUNT


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
        "prediction and the true object from the same pre-grasp pose, compare the joints. Every "
        "grasp of this table, the tabletop's too, is planned and lift-tested on the object "
        "alone, its table ignored (the paper's protocol: GraspIt! grasps the object by itself), "
        "so that the conditions' joint errors compare; grasping on a table is the benchmark's "
        "and the clutter table's.",
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
    """results.md: the run's header, how to read it, then the main tables part by part, each part
    followed by the registered tables placed after it (:data:`grasp.evaluate.tables.TABLES`), and
    the timings."""
    cfg = results["config"]
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
    for lines, section in MAIN.parts(results, bold=not smoke):
        parts += lines
        parts += _section(results, section)
    parts += [markdown_timings(results), ""]
    return "\n".join(parts)


def _section(results: dict, section: str) -> list[str]:
    """The lines of every table of :data:`~grasp.evaluate.tables.TABLES` placed in ``section``."""
    return [line for table in TABLES if table.section == section and table is not MAIN
            for line in table.markdown(results)]


def markdown_timings(results: dict) -> str:
    """Per-stage seconds (wall and CPU, summed over sequences) and the run's wall times."""
    t = results["timings_s"]
    wall, cpu = t["stages_wall_summed_over_sequences"], t["stages_cpu_summed_over_sequences"]
    workers = results["config"]["workers"]
    one, many = ("Ray actor", "Ray actors") if results["config"].get("ray") else (
        "worker process", "worker processes")
    lines = [
        f"## Timings (seconds; {workers} {many if workers > 1 else one})",
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
