"""A table's cells: means over sequences (with their standard errors) and how results.md writes
them."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from grasp.evaluate.config import GRASP_SUCCESS, HIGHER_IS_BETTER, JOINT_METRICS

#: The row label of the F-score a perfect completion (the 40³ target itself) gets.
CEILING_LABEL = "Ceiling: the 40³ target itself"


def mean_or_none(values: Iterable[float | None]) -> float | None:
    """Mean of the values that are not None, rounded to 4 places; None when there are none."""
    vals = [v for v in values if v is not None]
    return round(float(np.mean(vals)), 4) if vals else None


def mean_and_se(values: Iterable[float]) -> dict | None:
    """Mean and standard error (sample SD / √n) of per-sequence values, 4 places; the SE is
    None for one value; None for none."""
    vals = np.asarray(list(values), dtype=float)
    if vals.size == 0:
        return None
    se = float(np.std(vals, ddof=1) / np.sqrt(vals.size)) if vals.size > 1 else None
    return {"mean": round(float(vals.mean()), 4), "se": None if se is None else round(se, 4),
            "n": int(vals.size)}


def fmt(value: float | None, metric: str) -> str:
    if value is None:
        return "—"
    if metric == GRASP_SUCCESS:
        return f"{100 * value:.0f}%"
    return f"{value:.2f}°" if metric in JOINT_METRICS else f"{value:.2f}"


def best(values: list[float | None], metric: str) -> float | None:
    vals = [v for v in values if v is not None]
    if not vals:
        return None
    return max(vals) if HIGHER_IS_BETTER[metric] else min(vals)


def pm(block: dict | None, *, signed: bool = False) -> str:
    if block is None:
        return "—"
    mean = f"{block['mean']:+.3f}" if signed else f"{block['mean']:.3f}"
    return mean if block["se"] is None else f"{mean} ± {block['se']:.3f}"
