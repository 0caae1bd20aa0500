"""The overhead table: tabletop test sequences searched for views from above (elevation at least
:data:`OVERHEAD_MIN_ELEVATION_DEG`), where a completion is most tempted
to reach under the table: Jaccard and the share of the completion below the table."""

from __future__ import annotations

from typing import Any

from grasp.evaluate.cells import fmt, mean_or_none
from grasp.evaluate.config import ROW_LABELS, Job, Settings
from grasp.evaluate.sequence_result import SequenceResult
from grasp.evaluate.tables.base import Option, Table

OVERHEAD_TABLE = "overhead"
#: A view counts as from above at this elevation (degrees) or more.
OVERHEAD_MIN_ELEVATION_DEG = 75.0
#: ``--overhead N``: tabletop test sequences searched.
SIZE = Option(OVERHEAD_TABLE, "tabletop test sequences searched for overhead views, elevation ≥ "
              "75°, for the share of the completion below the table", quick=2, default=30,
              full=200)


class OverheadTable(Table):
    name, section, options = OVERHEAD_TABLE, "jaccard", (SIZE,)

    def jobs(self, settings: Settings) -> list[Job]:
        if "tabletop" not in settings.conditions:
            return []
        return [Job(OVERHEAD_TABLE, "tabletop", "test", index, light=True)
                for index in range(SIZE.of(settings))]

    def run(self, evaluator: Any, job: Job) -> SequenceResult:
        """Scored only when a view is from above (searched, none: nothing reaches the table)."""
        return evaluator.sequence(job, keep=lambda seq: max(seq.meta["elevation_deg"])
                                  >= OVERHEAD_MIN_ELEVATION_DEG)

    def summarise(self, results: list[SequenceResult], settings: Settings) -> dict:
        """``tabletop_overhead``: every view from above, per row: mean Jaccard and the mean share
        of the completion below the table (before any cut), with the target's own share (voxels
        the table's surface cuts) as the floor; None without such views."""
        views = [(r, v) for r in results if r.job.table == OVERHEAD_TABLE
                 for v, e in enumerate(r.elevation_deg) if e >= OVERHEAD_MIN_ELEVATION_DEG]
        if not views:
            return {"tabletop_overhead": None}
        return {"tabletop_overhead": {
            "min_elevation_deg": OVERHEAD_MIN_ELEVATION_DEG,
            "views": len(views),
            "sequences": len({id(r) for r, _ in views}),
            "searched": sum(r.job.table == OVERHEAD_TABLE for r in results),
            "jaccard": {row: mean_or_none(r.per_view[row]["jaccard"][v] for r, v in views)
                        for row in settings.rows},
            "below_plane_share": {row: mean_or_none(r.per_view[row]["below_plane"][v]
                                                    for r, v in views) for row in settings.rows},
            "target_below_plane_share": mean_or_none(r.ceiling["below_plane"][v]
                                                     for r, v in views),
        }}

    def markdown(self, results: dict) -> list[str]:
        block = results.get("tabletop_overhead")
        if not block:
            return []
        lines = [
            f"## Tabletop seen from above (elevation ≥ {block['min_elevation_deg']:.0f}°)",
            "",
            f"{block['views']} views of {block['sequences']} sequences (of {block['searched']} "
            "tabletop test sequences searched). Below the table: the share of the completion's "
            "voxels whose centre lies under the table top, before any cut; the target's own "
            f"share (voxels the table top cuts) is {block['target_below_plane_share']:.3f}.",
            "",
            "| Model | Jaccard | Share below the table |",
            "|---|---|---|",
        ]
        for row, j in block["jaccard"].items():
            share = block["below_plane_share"][row]
            lines.append(f"| {ROW_LABELS[row]} | {fmt(j, 'jaccard')} | "
                         f"{'—' if share is None else f'{share:.3f}'} |")
        return [*lines, ""]


TABLE = OverheadTable()
