"""How far Table I's Jaccard cells can be trusted: each cell's standard error over its sequences,
the paired differences from Single-View and from MVP's memory-off row, and how much the per-view
curve rises; computed for results.json (``jaccard_precision``) and written for results.md."""

from __future__ import annotations

import numpy as np

from grasp.evaluate.cells import mean_and_se, pm
from grasp.evaluate.config import (
    CONDITION_LABELS,
    MEMORY_OFF,
    REGISTERED,
    ROW_LABELS,
    TABLE_ORDER,
)
from grasp.evaluate.sequence_result import SequenceResult


def cell_precision(seqs: list[SequenceResult], row: str, rows: tuple[str, ...]) -> dict:
    """How far one Jaccard cell can be trusted, from its sequences (each a sample):
    ``cell`` mean ± SE; ``vs_single_view`` the paired difference row − Single-View on the same
    sequences (much tighter than two unpaired SEs); ``rise`` the mean of the last three views
    minus the first three per sequence (> 0: the curve rises, as working memory should), and
    ``rise_vs_single_view`` that rise minus Single-View's on the same sequence (what is left
    once the views' own difficulty, which both see, is taken out). For MVP with its memory-off
    row present, ``vs_memory_off`` and ``rise_vs_memory_off`` pair it with that row the same way:
    what the memory alone adds."""

    def rise(v: np.ndarray) -> float:
        return v[-3:].mean() - v[:3].mean()

    own = [np.asarray(r.per_view[row]["jaccard"]) for r in seqs]
    long = bool(own) and min(v.size for v in own) >= 6
    out = {"cell": mean_and_se(v.mean() for v in own),
           "rise": mean_and_se(rise(v) for v in own) if long else None}

    def versus(other: str, key: str) -> None:  # paired with another row on the same sequences
        pairs = [(v, np.asarray(r.per_view[other]["jaccard"]))
                 for v, r in zip(own, seqs, strict=True)]
        out[f"vs_{key}"] = mean_and_se(v.mean() - w.mean() for v, w in pairs)
        out[f"rise_vs_{key}"] = (mean_and_se(rise(v) - rise(w) for v, w in pairs)
                                 if long else None)  # fmt: skip

    out["vs_single_view"] = out["rise_vs_single_view"] = None
    if row != "single_view" and "single_view" in rows:
        versus("single_view", "single_view")
    if row == "mvp" and MEMORY_OFF in rows:
        versus(MEMORY_OFF, "memory_off")
    if row == REGISTERED and "mvp" in rows:
        versus("mvp", "mvp")
    return out


def markdown_precision(results: dict, split: str = "test") -> list[str]:
    """Table I's Jaccard with its standard errors over sequences, the paired difference of
    every row from Single-View, and how much each row's per-view curve rises."""
    precision = results.get("jaccard_precision") or {}
    rows = [r for r in precision if any(precision[r][c].get(split) for c in precision[r])]
    if not rows:
        return []
    conditions = [c for c in TABLE_ORDER if c in precision[rows[0]]]
    header = "| Model | " + " | ".join(CONDITION_LABELS[c] for c in conditions) + " |"
    rule = "|---|" + "---|" * len(conditions)

    def table(key: str, *, signed: bool) -> list[str]:
        lines = [header, rule]
        for row in rows:
            cells = [pm(precision[row][c].get(split, {}).get(key), signed=signed)
                     for c in conditions]
            if any(cell != "—" for cell in cells):
                lines.append(f"| {ROW_LABELS[row]} | " + " | ".join(cells) + " |")
        return lines

    n = results["config"]["count"]
    return [
        f"## How precise Table I is ({split} split, mean ± standard error over sequences)",
        "",
        f"Each cell of Table I averages {n} sequences, so it carries sampling noise: the standard "
        "error is the sample SD of the per-sequence Jaccard over √n (about ±2 SE is a 95% "
        "interval). Comparisons on the same sequences are tighter: the second table gives each "
        "row minus Single-View, paired sequence by sequence; the third the mean of the last "
        "three views minus the first three, per sequence (above 0: the per-view curve rises, as "
        "working memory should make it); the fourth that rise minus Single-View's on the same "
        "sequence, which takes out how hard the views themselves are. `jaccard_precision` in "
        "results.json has both splits.",
        "",
        "Jaccard:",
        "",
        *table("cell", signed=False),
        "",
        "Minus Single-View (paired):",
        "",
        *table("vs_single_view", signed=True),
        "",
        "Last three views minus the first three:",
        "",
        *table("rise", signed=True),
        "",
        "That rise minus Single-View's (paired):",
        "",
        *table("rise_vs_single_view", signed=True),
        "",
        *_paired_table(precision, conditions, split, "mvp", "memory_off",
                       "What the memory adds: MVP minus MVP with its memory off"),
        *_paired_table(precision, conditions, split, REGISTERED, "mvp",
                       "What the camera poses add: MVP + camera poses minus MVP"),
    ]


def _paired_table(precision: dict, conditions: list[str], split: str, row: str, key: str,
                  title: str) -> list[str]:
    """``row`` minus another row on the same sequences (``vs_<key>``): Jaccard and rise."""
    cells = precision.get(row, {})
    if not any(cells.get(c, {}).get(split, {}).get(f"vs_{key}") for c in conditions):
        return []
    lines = [f"{title}, on the same sequences (paired):", "",
             "| | " + " | ".join(CONDITION_LABELS[c] for c in conditions) + " |",
             "|---|" + "---|" * len(conditions)]
    for name, label in ((f"vs_{key}", "Jaccard"), (f"rise_vs_{key}", "Rise")):
        lines.append(f"| {label} | " + " | ".join(
            pm(cells.get(c, {}).get(split, {}).get(name), signed=True) for c in conditions) + " |")
    return [*lines, ""]
