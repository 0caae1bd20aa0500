"""From per-sequence results to the tables of results.json (means per cell, with their counts)."""

from __future__ import annotations

import numpy as np

from completion.scenes import CONDITIONS, SINGLE_OBJECT_CONDITIONS
from grasp.evaluate.cells import mean_or_none
from grasp.evaluate.config import (
    BENCHMARK_TABLE,
    EVAL_SPLITS,
    FSCORE_METRICS,
    GRASP_SUCCESS,
    MAIN_TABLE,
    METRICS,
    TRUE_MESH,
    Settings,
)
from grasp.evaluate.precision import cell_precision
from grasp.evaluate.records import SequenceResult
from hands.barrett import JOINT_NAMES

#: results.json key of each grasp metric inside a ``JointError.as_dict()``.
_JOINT_KEYS = {"joint_error_deg": "error_deg", "joint_error_moving_deg": "error_moving_deg"}


def aggregate(results: list[SequenceResult], settings: Settings, table: str) -> dict:
    """Tables for one set of sequences: metric -> row -> condition -> split -> value (or None).

    Also ``counts`` per cell (``sequences``; ``grasped``: sequences whose final view was grasped;
    ``grasp_ok``: of those, how many gave a comparable grasp, i.e. how many the joint-error cell
    averages), ``grasp_failures`` (the reasons of the others), ``per_view_jaccard`` (mean over
    sequences per view index), ``jaccard_precision`` (standard errors,
    :func:`grasp.evaluate.precision.cell_precision`),
    ``joint_error_per_joint_deg`` and, per condition and split, the F-score ``ceiling`` (the 40³
    target itself scored like a prediction).
    """
    mine = [r for r in results if r.job.table == table]
    conditions = sorted({r.job.condition for r in mine}, key=CONDITIONS.index)
    splits = [s for s in EVAL_SPLITS if any(r.job.split == s for r in mine)]

    def cell(c: str, s: str, grasped: bool = False) -> list[SequenceResult]:
        """The cell's completion sequences (``grasped``: and its grasp-only ones)."""
        return [r for r in mine if r.job.condition == c and r.job.split == s
                and (grasped or not r.job.grasp_only)]

    tables: dict = {m: {} for m in (*METRICS, GRASP_SUCCESS)}
    counts: dict = {}
    per_view: dict = {}
    failures: dict = {}
    per_joint: dict = {}
    precision: dict = {}
    for row in settings.rows:
        for m in METRICS:
            tables[m][row] = {c: {} for c in conditions}
        counts[row] = {c: {} for c in conditions}
        per_view[row] = {c: {} for c in conditions}
        failures[row] = {c: {} for c in conditions}
        per_joint[row] = {c: {} for c in conditions}
        precision[row] = {c: {} for c in conditions}
        for c in conditions:
            applies = c in SINGLE_OBJECT_CONDITIONS
            for s in splits:
                seqs = cell(c, s)
                for m in ("jaccard", *FSCORE_METRICS):
                    tables[m][row][c][s] = mean_or_none(np.mean(r.per_view[row][m]) for r in seqs)
                grasped = [r.grasps[row] for r in cell(c, s, True) if row in r.grasps]
                ok = [g for g in grasped if g["error_deg"] is not None]
                for m, key in _JOINT_KEYS.items():
                    tables[m][row][c][s] = mean_or_none(g[key] for g in ok) if applies else None
                joints = [g["per_joint_deg"] for g in ok]
                per_joint[row][c][s] = _by_joint(np.mean(joints, axis=0)) if joints else None
                counts[row][c][s] = {
                    "sequences": len(seqs),
                    "grasped": len(grasped),
                    "grasp_ok": len(ok),
                }
                failures[row][c][s] = sorted({g["reason"] for g in grasped if g["reason"]})
                views = [r.per_view[row]["jaccard"] for r in seqs]
                per_view[row][c][s] = np.round(np.mean(views, axis=0), 4).tolist() if seqs else []
                precision[row][c][s] = cell_precision(seqs, row, settings.rows)
    success_counts: dict = {}
    for row in (*settings.rows, TRUE_MESH):
        tables[GRASP_SUCCESS][row] = {c: {} for c in conditions}
        success_counts[row] = {c: {} for c in conditions}
        for c in conditions:
            for s in splits:
                tested = [r.physics[row] for r in cell(c, s, True) if row in r.physics]
                held = sum(t["success"] for t in tested)
                applies = c in SINGLE_OBJECT_CONDITIONS and tested
                tables[GRASP_SUCCESS][row][c][s] = round(held / len(tested), 4) if applies else None
                success_counts[row][c][s] = {"tested": len(tested), "held": held}
    ceiling = {
        c: {
            s: {m: mean_or_none(np.mean(r.ceiling[m]) for r in cell(c, s)) for m in FSCORE_METRICS}
            for s in splits
        }
        for c in conditions
    }
    return {
        "tables": tables,
        "counts": counts,
        "grasp_success_counts": success_counts,
        "per_view_jaccard": per_view,
        "jaccard_precision": precision,
        "grasp_failures": failures,
        "joint_error_per_joint_deg": per_joint,
        "ceiling": ceiling,
        "conditions": conditions,
        "splits": splits,
    }


def fscore_ceiling(ceiling: dict) -> dict:
    """results.json's ``fscore_ceiling``: per condition F@1% and F@2% of a perfect completion
    (mean over both splits' sequences, each weighted alike) and the per-split values."""
    out = {}
    for c, by_split in ceiling.items():
        out[c] = {
            m: mean_or_none(v[m] for v in by_split.values()) for m in FSCORE_METRICS
        } | {"by_split": by_split}
    return out


def per_object_records(results: list[SequenceResult], settings: Settings) -> list[dict]:
    records = []
    for r in results:
        if r.job.table == BENCHMARK_TABLE:
            records.append({"table": r.job.table, "index": r.job.index,
                            "object_ids": r.object_ids, "benchmark": r.benchmark["rows"]})
            continue
        if not r.per_view:  # an overhead search without a view from above: not completed
            continue
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
