"""Everything results.json holds, from the per-sequence results of one run: every table's entries
(:data:`grasp.evaluate.tables.TABLES`), one record per sequence and row, the configuration and the
timings."""

from __future__ import annotations

from grasp.evaluate.aggregate import per_object_records
from grasp.evaluate.config import PAPER_TABLES, Settings, config_dict
from grasp.evaluate.records import SequenceResult, Timings
from grasp.evaluate.tables import TABLES


def build_results(results: list[SequenceResult], settings: Settings, wall: dict) -> dict:
    """Everything results.json holds, from the per-sequence results of one run."""
    timings = Timings()
    for r in results:
        timings.add(r.timings)
    out: dict = {}
    for table in TABLES:  # each table's own entries, the main table's first
        out.update(table.summarise(results, settings))
    out |= {
        "per_object": per_object_records(results, settings),
        "config": config_dict(settings),
        "paper_tables": PAPER_TABLES,
        "timings_s": {
            "stages_wall_summed_over_sequences": {k: round(v, 2) for k, v in timings.wall.items()},
            "stages_cpu_summed_over_sequences": {k: round(v, 2) for k, v in timings.cpu.items()},
            "wall": {k: round(v, 2) for k, v in wall.items()},
        },
    }
    return out
