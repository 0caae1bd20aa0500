"""Everything results.json holds, from the per-sequence results of one run: the main tables
(:mod:`grasp.evaluate.aggregate`), every other table's entries
(:data:`grasp.evaluate.tables.TABLES`), the configuration and the timings."""

from __future__ import annotations

from grasp.evaluate.aggregate import (
    aggregate,
    fscore_ceiling,
    per_object_records,
    pooled_per_joint,
)
from grasp.evaluate.config import MAIN_TABLE, PAPER_TABLES, Settings, config_dict
from grasp.evaluate.records import SequenceResult, Timings
from grasp.evaluate.tables import TABLES


def build_results(results: list[SequenceResult], settings: Settings, wall: dict) -> dict:
    """Everything results.json holds, from the per-sequence results of one run."""
    timings = Timings()
    for r in results:
        timings.add(r.timings)
    main = aggregate(results, settings, MAIN_TABLE)
    out = {
        "tables": main["tables"],
        "counts": main["counts"],
        "fscore_ceiling": fscore_ceiling(main["ceiling"]),
        "grasp_success_counts": main["grasp_success_counts"],
        "grasp_failures": main["grasp_failures"],
        "joint_error_per_joint_deg": main["joint_error_per_joint_deg"],
        "pooled_joint_error_per_joint_deg": pooled_per_joint(results, settings),
        "per_view_jaccard": main["per_view_jaccard"],
        "jaccard_precision": main["jaccard_precision"],
        "per_object": per_object_records(results, settings),
        "config": config_dict(settings),
        "paper_tables": PAPER_TABLES,
        "timings_s": {
            "stages_wall_summed_over_sequences": {k: round(v, 2) for k, v in timings.wall.items()},
            "stages_cpu_summed_over_sequences": {k: round(v, 2) for k, v in timings.cpu.items()},
            "wall": {k: round(v, 2) for k, v in wall.items()},
        },
    }
    for table in TABLES:  # their own entries
        out.update(table.summarise(results, settings))
    return out
