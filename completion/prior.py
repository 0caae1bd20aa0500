"""The input-free reference of the evaluation: one fixed shape placed in every view's grid.

Each view's grid is fitted to what the camera saw (docs/design.md §3), so the frame alone already
says where the object is and how big: a shape that ignores the input scores well above zero. The
prior row of ``python -m grasp.evaluate`` measures how much: it is the voxel-wise mean of the
training targets of the condition (all views), thresholded where the validation set's mean Jaccard
is highest. A model row is only worth what it adds over this row.

    python -m completion.prior --train-dir data/train --val-dir data/val \\
        --out completion/weights/prior.npz

One shape per condition (each fits its grid its own way). The file holds ``conditions``,
``means`` (one 40³ float16 grid each: the share of training targets occupying each voxel),
``thresholds`` and ``meta`` (JSON: the command, the number of grids, the validation sweeps).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from completion.cli import DefaultsAndRawDescription
from completion.grid import GRID_SHAPE, jaccard

__all__ = ["Prior", "build_prior", "load_prior", "main"]

#: Thresholds tried on the validation set.
THRESHOLDS = tuple(round(x, 2) for x in np.arange(0.05, 0.96, 0.05))
PRIOR_FILE = "prior.npz"


@dataclass(frozen=True)
class Prior:
    """Per condition: mean (40, 40, 40) float32 in [0, 1] and the threshold where it becomes
    occupied. The frame is fitted differently per condition (a curtain hides part of the object
    in object hiding/reveal, two objects share the grid in two-object pan), so each has its own."""

    means: dict[str, np.ndarray]
    thresholds: dict[str, float]
    meta: dict

    def probabilities(self, condition: str, views: int) -> np.ndarray:
        """(views, 40, 40, 40) float32: the condition's shape, the same in every view's grid."""
        if condition not in self.means:
            raise ValueError(f"the prior has no {condition!r}; it has {sorted(self.means)}")
        return np.broadcast_to(self.means[condition], (views, *GRID_SHAPE)).copy()


def _targets(split: dict, condition: str, chunk: int = 64):
    """Unpacked (n, L, 40, 40, 40) bool targets of one condition, ``chunk`` sequences at a time."""
    rows = np.flatnonzero(np.asarray(split["condition"]) == condition)
    for start in range(0, len(rows), chunk):
        yield np.unpackbits(split["packed"][rows[start : start + chunk], 1], axis=-1).astype(bool)


def build_prior(train: dict, val: dict) -> Prior:
    """Per condition, the voxel-wise mean of the training targets, thresholded for the best mean
    validation Jaccard. ``train`` and ``val`` as :func:`completion.validation.load_split`
    returns them.
    """
    means, thresholds, meta = {}, {}, {"train_grids": {}, "val_jaccard": {}}
    for condition in sorted(set(train["condition"])):
        total, count = np.zeros(GRID_SHAPE, np.float64), 0
        for targets in _targets(train, condition):
            total += targets.sum(axis=(0, 1))
            count += targets.shape[0] * targets.shape[1]
        mean = (total / count).astype(np.float32)
        scores: dict[float, list[float]] = {t: [] for t in THRESHOLDS}
        for targets in _targets(val, condition):
            for t in THRESHOLDS:
                scores[t] += jaccard(targets, mean >= t).reshape(-1).tolist()
        if not scores[THRESHOLDS[0]]:
            raise ValueError(f"no validation sequences of {condition!r} to choose a threshold on")
        sweep = {f"{t:.2f}": round(float(np.mean(v)), 4) for t, v in scores.items()}
        best = max(THRESHOLDS, key=lambda t: sweep[f"{t:.2f}"])
        means[condition], thresholds[condition] = mean, float(best)
        meta["train_grids"][condition] = count
        meta["val_jaccard"][condition] = sweep
    return Prior(means, thresholds, meta)


def save_prior(prior: Prior, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    conditions = sorted(prior.means)
    np.savez_compressed(
        path,
        conditions=np.array(conditions),
        means=np.stack([prior.means[c] for c in conditions]).astype(np.float16),
        thresholds=np.array([prior.thresholds[c] for c in conditions]),
        meta=np.array(json.dumps(prior.meta)),
    )
    return path


def load_prior(path: str | Path) -> Prior:
    """Read a prior file; ValueError naming the file when it is not one."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            conditions = [str(c) for c in z["conditions"]]
            means = z["means"].astype(np.float32)
            thresholds = [float(t) for t in z["thresholds"]]
            meta = json.loads(str(z["meta"]))
    except (OSError, KeyError, ValueError) as exc:
        raise ValueError(f"{path} is not a prior file: {exc}") from exc
    if means.shape != (len(conditions), *GRID_SHAPE) or not all(0 < t < 1 for t in thresholds):
        raise ValueError(f"{path}: expected one {GRID_SHAPE} mean and threshold per condition")
    return Prior(dict(zip(conditions, means, strict=True)),
                 dict(zip(conditions, thresholds, strict=True)), meta)


def main(argv: list[str] | None = None) -> int:
    from completion.scenes import CONDITIONS
    from completion.validation import load_split

    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(prog="python -m completion.prior", description=__doc__,
                                formatter_class=DefaultsAndRawDescription)
    p.add_argument("--train-dir", type=Path, default=Path("data/train"))
    p.add_argument("--val-dir", type=Path, default=Path("data/val"))
    p.add_argument("--out", type=Path, default=Path("completion/weights") / PRIOR_FILE)
    args = p.parse_args(argv)
    try:
        train = load_split(args.train_dir, list(CONDITIONS), "train")
        val = load_split(args.val_dir, list(CONDITIONS), "val")
    except ValueError as exc:
        p.error(f"{exc} (generate shards with `python -m completion.data generate …`)")
    prior = build_prior(train, val)
    prior.meta["command"] = "python -m completion.prior " + shlex.join(argv)
    prior.meta["train_sequences"] = len(train["packed"])
    save_prior(prior, args.out)
    print(f"wrote {args.out}")
    for c, t in prior.thresholds.items():
        print(f"  {c}: mean of {prior.meta['train_grids'][c]} training targets, threshold "
              f"{t:.2f}, validation Jaccard {prior.meta['val_jaccard'][c][f'{t:.2f}']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
