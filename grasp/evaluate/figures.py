"""The figures of an evaluation: per-view Jaccard, example completions, grasps."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from completion import grid as G
from completion.bullet import quiet_fds
from completion.grid import VoxelGrid
from completion.scenes import Sequence
from grasp.evaluate.config import (
    CONDITION_LABELS,
    PAPER_ORDER,
    REFERENCE_ROWS,
    ROW_LABELS,
    figure_rows,
)
from grasp.evaluate.runner import truth_mesh_in_latest_camera
from grasp.evaluate.sequence_result import SequenceResult
from grasp.evaluate.tables import TABLES


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
    """jaccard_per_view.png, examples.png and grasps.png (when there are grasps), and each
    table's own (:meth:`grasp.evaluate.tables.base.Table.figures`)."""
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
                style = "--" if row in REFERENCE_ROWS else "-"
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
                VoxelGrid.unpack(ex["input"].tobytes()),
                VoxelGrid.unpack(ex["target"].tobytes()),
                *[VoxelGrid.unpack(ex["rows"][n].tobytes()) for n in row_names],
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

    grasps = _grasp_figure(raw, out, plt)
    written += [] if grasps is None else [grasps]
    for table in TABLES:
        written += table.figures(raw, out, plt, seed=results["config"]["seed"])
    return written


#: Examples shown in grasps.png (main table first: camera pan, hiding, reveal).
GRASP_FIGURE_EXAMPLES = 3


def _grasp_result(summary: dict):
    """A ``GraspResult`` carrying the pose and joints of a JSON grasp summary (for rendering)."""
    from grasp.hand.result import GraspResult, HandDofs, HandJoints

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

    Rendered with :func:`grasp.evaluate.render.render_grasp` (pybullet TinyRenderer, side view).
    """
    from grasp.evaluate import metrics
    from grasp.evaluate.render import render_grasp

    shown = [r for r in raw if r.example is not None and r.grasps][:GRASP_FIGURE_EXAMPLES]
    if not shown:
        return None
    rows = figure_rows(list(shown[0].grasps))
    cols = [(n, side) for n in rows for side in ("on_prediction", "on_truth")]
    fig, axes = plt.subplots(
        len(shown),
        len(cols),
        figsize=(2.4 * len(cols), 2.9 * len(shown) + 0.5),
        squeeze=False,
        layout="constrained",  # titles of two lines never run into the row above
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
            with quiet_fds(1):
                image = render_grasp(mesh, _grasp_result(g[side]), width=240, height=240)[0]
            ax.imshow(image)
    fig.suptitle(
        "Grasp planned on the completion, and the same pre-grasp re-run on the truth", fontsize=9
    )
    path = out / "grasps.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
