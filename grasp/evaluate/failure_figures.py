"""A figure of a table's failed grasps, each the scene on a patch of its table and the hand: the
benchmark's (benchmark_failures.png) and the clutter table's (clutter_failures.png)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from completion.bullet import quiet_fds

#: Failed grasps a table's failures figure shows, at most (:func:`failures_figure`).
FAILURE_FIGURE_EXAMPLES = 12


def failures_figure(raw, out: Path, plt, table: str, row: str, scene, title, heading: str,
                    name: str, key: str = "held") -> Path | None:
    """A figure of ``table``'s ``row`` grasps whose ``key`` is false (at most
    :data:`FAILURE_FIGURE_EXAMPLES`), each the meshes ``scene(r)`` gives on a patch of the
    table and the hand where it closed (as planned in a record without that pose), titled
    ``title(r, record)`` and the reason; ``record`` is the row's outcome in the job's record
    (``r.record["rows"][row]``)."""
    import textwrap

    from grasp.evaluate.render import render_grasp
    from grasp.hand.result import GraspResult, HandDofs, HandJoints

    failed = [r for r in raw if r.job.table == table and "palm_pose" in r.record.get(
        "rows", {}).get(row, {}) and not r.record["rows"][row][key]]
    failed = failed[:FAILURE_FIGURE_EXAMPLES]
    if not failed:
        return None
    cols = min(4, len(failed))
    rows = -(-len(failed) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.6 * rows), squeeze=False,
                             layout="constrained")
    for ax in axes.flat:
        ax.axis("off")
    for ax, r in zip(axes.flat, failed, strict=False):
        record = r.record["rows"][row]
        meshes = scene(r)
        ax.set_title(textwrap.fill(title(r, record) + record["reason"], 44), fontsize=7)
        lo, hi = trimesh.util.concatenate(meshes).bounds
        patch = trimesh.creation.box([1.2 * (hi - lo)[0] + 0.02, 1.2 * (hi - lo)[1] + 0.02,
                                      0.002])
        patch.apply_translation([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, -0.001])
        palm = record.get("end_palm_pose", record["palm_pose"])  # where the fingers closed
        hand = GraspResult(False, record["reason"], np.asarray(palm),
                           HandJoints(*record["planned_joints_deg"]),
                           HandDofs(record["planned_joints_deg"][0], 0.0, 0.0, 0.0))
        with quiet_fds(1):
            image = render_grasp(trimesh.util.concatenate([*meshes, patch]), hand, width=260,
                                 height=260)[0]
        ax.imshow(image)
    fig.suptitle(heading, fontsize=9)
    path = out / name
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
