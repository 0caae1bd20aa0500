"""A figure of a table's failed grasps, each the scene on a patch of its table and the hand: the
benchmark's (benchmark_failures.png) and the clutter table's (clutter_failures.png)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from completion.bullet import quiet_fds

#: Failed grasps a table's failures figure shows, at most (:func:`failures_figure`).
FAILURE_FIGURE_EXAMPLES = 12
#: Colours of the figure's parts (RGBA): the target is :class:`~grasp.evaluate.picture.GraspWorld`'s
#: orange, the hand its grey; none of them is another's.
TARGET_RGBA = (0.85, 0.55, 0.3, 1.0)
NEIGHBOUR_RGBA = (0.35, 0.55, 0.85, 1.0)
TABLE_RGBA = (0.62, 0.76, 0.58, 1.0)
HAND_RGBA = (0.45, 0.45, 0.5, 1.0)  # the legend's: the palm is darker, the fingers lighter
#: Characters of the heading per inch of figure width (9-point type).
HEADING_CHARS_PER_INCH = 14


def failures_figure(raw, out: Path, plt, table: str, row: str, scene, title, heading: str,
                    name: str, key: str = "held") -> Path | None:
    """A figure of ``table``'s ``row`` grasps whose ``key`` is false (at most
    :data:`FAILURE_FIGURE_EXAMPLES`), each the meshes ``scene(r)`` gives (the target first, then
    its neighbours, each coloured apart) on a patch of the table and the hand where it closed (as
    planned in a record without that pose), titled ``title(r, record)`` and the reason; ``record``
    is the row's outcome in the job's record (``r.record["rows"][row]``). A legend names the
    colours; the heading is wrapped to the figure's width."""
    import textwrap

    from matplotlib.patches import Patch

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
    with_neighbours = False
    for ax, r in zip(axes.flat, failed, strict=False):
        record = r.record["rows"][row]
        meshes = scene(r)
        with_neighbours |= len(meshes) > 1
        ax.set_title(textwrap.fill(title(r, record) + record["reason"], 44), fontsize=7)
        lo, hi = trimesh.util.concatenate(meshes).bounds
        patch = trimesh.creation.box([1.2 * (hi - lo)[0] + 0.02, 1.2 * (hi - lo)[1] + 0.02,
                                      0.002])
        patch.apply_translation([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, -0.001])
        palm = record.get("end_palm_pose", record["palm_pose"])  # where the fingers closed
        hand = GraspResult(False, record["reason"], np.asarray(palm),
                           HandJoints(*record["planned_joints_deg"]),
                           HandDofs(record["planned_joints_deg"][0], 0.0, 0.0, 0.0))
        others = [(patch, TABLE_RGBA), *((m, NEIGHBOUR_RGBA) for m in meshes[1:])]
        with quiet_fds(1):
            image = render_grasp(meshes[0], hand, width=260, height=260, others=others,
                                 above=(0.0, 0.0, 1.0))[0]  # the scenes' table: z = 0
        ax.imshow(image)
    width_in = fig.get_size_inches()[0]
    fig.suptitle(textwrap.fill(heading, int(HEADING_CHARS_PER_INCH * width_in)), fontsize=9)
    parts = [("target", TARGET_RGBA), ("table", TABLE_RGBA), ("hand", HAND_RGBA)]
    if with_neighbours:
        parts.insert(1, ("neighbours", NEIGHBOUR_RGBA))
    fig.legend(handles=[Patch(color=rgba, label=label) for label, rgba in parts],
               loc="outside lower center", ncols=len(parts), fontsize=7, frameon=False)
    path = out / name
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
