"""Everything results.json holds, from the per-sequence results of one run: every table's entries
(:data:`grasp.evaluate.tables.TABLES`), one record per sequence and row, the configuration and the
timings."""

from __future__ import annotations

from dataclasses import asdict

from grasp.evaluate.config import EVAL_SPLITS, PAPER_TABLES, Settings
from grasp.evaluate.sequence_result import STAGES, SequenceResult, Timings
from grasp.evaluate.tables import BY_NAME, OPTIONS, TABLES


def build_results(results: list[SequenceResult], settings: Settings, wall: dict) -> dict:
    """Everything results.json holds, from the per-sequence results of one run."""
    timings = Timings()
    for r in results:
        timings.add(r.timings)
    out: dict = {}
    for table in TABLES:  # each table's own entries, the main table's first
        out.update(table.summarise(results, settings))
    stages = [*STAGES, *(stage for table in TABLES for stage in table.stages)]
    stages += [k for k in timings.wall if k not in stages]  # one a table charged undeclared
    out |= {
        "per_object": [record for r in results
                       for record in BY_NAME[r.job.table].records(r, settings)],
        "config": config_dict(settings),
        "paper_tables": PAPER_TABLES,
        "timings_s": {
            "stages_wall_summed_over_sequences": {k: round(timings.wall.get(k, 0.0), 2)
                                                  for k in stages},
            "stages_cpu_summed_over_sequences": {k: round(timings.cpu.get(k, 0.0), 2)
                                                 for k in stages},
            "wall": {k: round(v, 2) for k, v in wall.items()},
        },
    }
    return out


def config_dict(settings: Settings) -> dict:
    """results.json's ``config``: the settings as plain JSON, each table's option under its name
    (its default where the settings name none)."""
    d = asdict(settings)
    del d["options"]
    d |= {name: option.of(settings) for name, option in OPTIONS.items()}
    d["model_paths"] = dict(settings.model_paths)
    d["objects"] = list(settings.objects)
    d["fscore_fractions"] = [0.01, 0.02]
    d["splits"] = list(EVAL_SPLITS)
    return d
