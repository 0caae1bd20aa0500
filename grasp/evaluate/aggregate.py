"""From per-sequence results to the tables of results.json (means per cell, with their counts)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from completion.scenes import CONDITIONS, SINGLE_OBJECT_CONDITIONS
from grasp.evaluate.cells import mean_or_none
from grasp.evaluate.config import (
    EVAL_SPLITS,
    FSCORE_METRICS,
    GRASP_SUCCESS,
    MAIN_TABLE,
    METRICS,
    TRUE_MESH,
    Settings,
)
from grasp.evaluate.precision import cell_precision
from grasp.evaluate.sequence_result import SequenceResult
from hands.barrett import JOINT_NAMES

#: results.json key of each grasp metric inside a ``JointError.as_dict()``.
_JOINT_KEYS = {"joint_error_deg": "error_deg", "joint_error_moving_deg": "error_moving_deg"}


@dataclass(frozen=True)
class Cell:
    """One row on one condition and split of a table: every figure results.json gives it."""

    row: str
    condition: str
    split: str
    values: dict[str, float | None]  # metric -> the cell of Tables I–III (None: n/a or none)
    counts: dict[str, int]  # sequences; grasped; grasp_ok (how many the joint error averages)
    failures: list[str]  # why the other grasps gave nothing comparable
    per_view_jaccard: list[float]  # mean over the cell's sequences per view index
    precision: dict  # grasp.evaluate.precision.cell_precision
    per_joint: dict[str, float] | None  # joint -> mean |Δθ| of the comparable grasps


@dataclass(frozen=True)
class SuccessCell:
    """One row's lift tests on one condition and split (the true-mesh row included)."""

    row: str
    condition: str
    split: str
    rate: float | None  # held / tested (None: n/a or nothing tested)
    counts: dict[str, int]  # tested, held


def aggregate(results: list[SequenceResult], settings: Settings, table: str) -> dict:
    """Tables for one set of sequences: metric -> row -> condition -> split -> value (or None).

    The cells are computed as records (:class:`Cell`, :class:`SuccessCell`), one per row,
    condition and split, and grouped into results.json's layout at the end: ``tables``,
    ``counts``, ``grasp_failures``, ``per_view_jaccard``, ``jaccard_precision``,
    ``joint_error_per_joint_deg``, ``grasp_success_counts`` and, per condition and split, the
    F-score ``ceiling`` (the 40³ target itself scored like a prediction).
    """
    mine = [r for r in results if r.job.table == table]
    conditions = sorted({r.job.condition for r in mine}, key=CONDITIONS.index)
    splits = [s for s in EVAL_SPLITS if any(r.job.split == s for r in mine)]

    def sequences(c: str, s: str, grasped: bool = False) -> list[SequenceResult]:
        """The cell's completion sequences (``grasped``: and its grasp-only ones)."""
        return [r for r in mine if r.job.condition == c and r.job.split == s
                and (grasped or not r.job.grasp_only)]

    cells = [_cell(row, c, s, sequences(c, s), sequences(c, s, True), settings.rows)
             for row in settings.rows for c in conditions for s in splits]
    success = [_success_cell(row, c, s, sequences(c, s, True))
               for row in (*settings.rows, TRUE_MESH) for c in conditions for s in splits]

    def nest(records, value, rows) -> dict:  # row -> condition -> split -> value(record)
        out = {row: {c: {} for c in conditions} for row in rows}
        for r in records:
            out[r.row][r.condition][r.split] = value(r)
        return out

    rows, with_truth = settings.rows, (*settings.rows, TRUE_MESH)
    tables = {m: nest(cells, lambda r, m=m: r.values[m], rows) for m in METRICS}
    tables[GRASP_SUCCESS] = nest(success, lambda r: r.rate, with_truth)
    ceiling = {c: {s: {m: mean_or_none(np.mean(r.ceiling[m]) for r in sequences(c, s))
                       for m in FSCORE_METRICS} for s in splits} for c in conditions}
    return {
        "tables": tables,
        "counts": nest(cells, lambda r: r.counts, rows),
        "grasp_success_counts": nest(success, lambda r: r.counts, with_truth),
        "per_view_jaccard": nest(cells, lambda r: r.per_view_jaccard, rows),
        "jaccard_precision": nest(cells, lambda r: r.precision, rows),
        "grasp_failures": nest(cells, lambda r: r.failures, rows),
        "joint_error_per_joint_deg": nest(cells, lambda r: r.per_joint, rows),
        "ceiling": ceiling,
        "conditions": conditions,
        "splits": splits,
    }


def _cell(row: str, c: str, s: str, seqs: list[SequenceResult],
          with_grasp_only: list[SequenceResult], rows: tuple[str, ...]) -> Cell:
    applies = c in SINGLE_OBJECT_CONDITIONS
    values = {m: mean_or_none(np.mean(r.per_view[row][m]) for r in seqs)
              for m in ("jaccard", *FSCORE_METRICS)}
    grasped = [r.grasps[row] for r in with_grasp_only if row in r.grasps]
    ok = [g for g in grasped if g["error_deg"] is not None]
    for m, key in _JOINT_KEYS.items():
        values[m] = mean_or_none(g[key] for g in ok) if applies else None
    joints = [g["per_joint_deg"] for g in ok]
    views = [r.per_view[row]["jaccard"] for r in seqs]
    return Cell(
        row, c, s, values,
        counts={"sequences": len(seqs), "grasped": len(grasped), "grasp_ok": len(ok)},
        failures=sorted({g["reason"] for g in grasped if g["reason"]}),
        per_view_jaccard=np.round(np.mean(views, axis=0), 4).tolist() if seqs else [],
        precision=cell_precision(seqs, row, rows),
        per_joint=_by_joint(np.mean(joints, axis=0)) if joints else None,
    )


def _success_cell(row: str, c: str, s: str, seqs: list[SequenceResult]) -> SuccessCell:
    tested = [r.physics[row] for r in seqs if row in r.physics]
    held = sum(t["success"] for t in tested)
    applies = c in SINGLE_OBJECT_CONDITIONS and tested
    return SuccessCell(row, c, s, round(held / len(tested), 4) if applies else None,
                       {"tested": len(tested), "held": held})


def fscore_ceiling(ceiling: dict) -> dict:
    """results.json's ``fscore_ceiling``: per condition F@1% and F@2% of a perfect completion
    (mean over both splits' sequences, each weighted alike) and the per-split values."""
    out = {}
    for c, by_split in ceiling.items():
        out[c] = {
            m: mean_or_none(v[m] for v in by_split.values()) for m in FSCORE_METRICS
        } | {"by_split": by_split}
    return out


def sequence_records(r: SequenceResult, settings: Settings) -> list[dict]:
    """results.json's ``per_object`` records of a sequence scored like the main table's: one per
    row (none for a sequence not scored, such as an overhead search without a view from
    above)."""
    if not r.per_view:
        return []
    records = []
    for row in settings.rows:
        g = r.grasps.get(row)
        records.append(
            {
                "table": r.job.table,
                "condition": r.job.condition,
                "split": r.job.split,
                "index": r.job.index,
                "object_ids": r.object_ids,
                "model": row,
                "jaccard": mean_or_none(r.per_view[row]["jaccard"]),
                "fscore_1": mean_or_none(r.per_view[row]["fscore_1"]),
                "fscore_2": mean_or_none(r.per_view[row]["fscore_2"]),
                "jaccard_per_view": [round(v, 4) for v in r.per_view[row]["jaccard"]],
                "joint_error_deg": None if g is None else g["error_deg"],
                "joint_error_moving_deg": None if g is None else g["error_moving_deg"],
                "joint_error_per_joint_deg": None if g is None else g["per_joint_deg"],
                "grasp": g,
            }
        )
    return records


def _by_joint(values: np.ndarray) -> dict[str, float]:
    return dict(zip(JOINT_NAMES, np.round(values, 4).tolist(), strict=True))


def pooled_per_joint(results: list[SequenceResult], settings: Settings) -> dict:
    """row -> joint -> mean |Δθ| over every grasped main-table sequence (both splits)."""
    out = {}
    for row in settings.rows:
        joints = [
            r.grasps[row]["per_joint_deg"]
            for r in results
            if r.job.table == MAIN_TABLE
            and row in r.grasps
            and r.grasps[row]["per_joint_deg"] is not None
        ]
        out[row] = _by_joint(np.mean(joints, axis=0)) if joints else None
    return out
