"""The sensor table: each condition's first test sequences seen with and without the sensor model
(completion.depth_camera.SensorModel), paired sequence by sequence (Jaccard only)."""

from __future__ import annotations

import numpy as np

from completion.scenes import CONDITIONS, NOISY_BY_DEFAULT
from grasp.evaluate.cells import mean_and_se, pm
from grasp.evaluate.config import (
    CONDITION_LABELS,
    MAIN_TABLE,
    ROW_LABELS,
    TABLE_ORDER,
    Job,
    Settings,
)
from grasp.evaluate.sequence_result import SequenceResult
from grasp.evaluate.tables.base import Option, Table

SENSOR_TABLE = "sensor"
#: ``--sensor N`` (``--no-sensor``: 0): test sequences per condition.
SIZE = Option(SENSOR_TABLE, "test sequences per condition seen with and without the sensor model, "
              "paired, Jaccard only", quick=1, default=5, full=50, negatable=True)


class SensorTable(Table):
    name, section, options = SENSOR_TABLE, "jaccard", (SIZE,)

    def jobs(self, settings: Settings) -> list[Job]:
        """Each condition with and without the sensor model, the same sequences; the main table
        has one side of the first ``count`` of them (noiseless for the paper's five)."""
        jobs = []
        for condition in settings.conditions:
            for index in range(SIZE.of(settings)):
                for noise in (True, False):
                    if noise != (condition in NOISY_BY_DEFAULT) or index >= settings.count:
                        jobs.append(Job(SENSOR_TABLE, condition, "test", index, noise=noise,
                                        light=True))
        return jobs

    def summarise(self, results: list[SequenceResult], settings: Settings) -> dict:
        """``sensor_noise``: the test split's first ``--sensor`` sequences of each
        condition seen through the sensor model (``jaccard``) and the very same sequences without
        it (``noiseless``), each a mean ± SE per row and condition, and their paired
        ``difference`` (mean ± SE of the per-sequence differences); None when the run has no
        sensor table. One side comes from the main table where it has the sequence."""
        if not any(r.job.table == SENSOR_TABLE for r in results):
            return {"sensor_noise": None}

        def noisy(r: SequenceResult) -> bool:
            return r.job.condition in NOISY_BY_DEFAULT if r.job.noise is None else r.job.noise

        sides: dict[tuple[str, bool], dict[int, SequenceResult]] = {}
        for r in results:
            main = r.job.table == MAIN_TABLE and r.job.split == "test"
            if r.job.table == SENSOR_TABLE or (main and r.job.index < SIZE.of(settings)):
                sides.setdefault((r.job.condition, noisy(r)), {})[r.job.index] = r
        conditions = sorted({c for c, _ in sides}, key=CONDITIONS.index)
        out: dict = {"split": "test", "jaccard": {}, "noiseless": {}, "difference": {}, "n": {}}
        for row in settings.rows:
            for key in ("jaccard", "noiseless", "difference", "n"):
                out[key][row] = {}
            for c in conditions:
                with_sensor, without = sides.get((c, True), {}), sides.get((c, False), {})
                paired = sorted(set(with_sensor) & set(without))
                a, b = ([float(np.mean(side[i].per_view[row]["jaccard"])) for i in paired]
                        for side in (with_sensor, without))
                out["jaccard"][row][c] = mean_and_se(a)
                out["noiseless"][row][c] = mean_and_se(b)
                out["difference"][row][c] = mean_and_se([x - y for x, y in zip(a, b, strict=True)])
                out["n"][row][c] = len(paired)
        return {"sensor_noise": out}

    def markdown(self, results: dict) -> list[str]:
        block = results.get("sensor_noise")
        if not block:
            return []
        rows = list(block["jaccard"])
        conditions = [c for c in TABLE_ORDER if c in block["jaccard"][rows[0]]]
        n = max(v for per in block["n"].values() for v in per.values())
        lines = [
            "## Jaccard with the sensor model on and off (test split, the same sequences)",
            "",
            f"Each cell: Jaccard ± SE over {n} sequences seen through completion.depth_camera."
            "SensorModel, then, in brackets, the mean paired difference from the same sequences "
            "rendered without it (on by default for tabletop, off for the paper's five); the input "
            "is cleaned as completion/depth.py says in both.",
            "",
            "| Model | " + " | ".join(CONDITION_LABELS[c] for c in conditions) + " |",
            "|---|" + "---|" * len(conditions),
        ]
        for row in rows:
            cells = []
            for c in conditions:
                d = block["difference"][row][c]
                cells.append(pm(block["jaccard"][row][c])
                             + ("" if d is None else f" ({d['mean']:+.3f})"))
            lines.append(f"| {ROW_LABELS[row]} | " + " | ".join(cells) + " |")
        return [*lines, ""]


TABLE = SensorTable()
