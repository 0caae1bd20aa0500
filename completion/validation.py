"""Validation of completion checkpoints: the Jaccard sweep training keeps, one threshold for all
models, what the memory adds view by view, and the model card's tables.

    python -m completion.train select-threshold completion/weights/*.pt
    python -m completion.train per-view completion/weights/mvp.pt data/val
    python -m completion.train model-card completion/weights/*.pt
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import torch

from completion.data import load_sequence
from completion.evidence import registered_surfaces
from completion.grid import jaccard
from completion.model import CompletionModel, load_checkpoint, read_checkpoint
from completion.scenes import CONDITIONS

THRESHOLDS = tuple(round(x, 2) for x in np.arange(0.2, 0.81, 0.05))


def load_split(folder: Path, conditions: list[str], split: str, *,
               registered: bool = False) -> dict:
    """Every shard of the given conditions in ``folder``, bit-packed in memory.

    ``packed``: uint8 (N, 2, L, 40, 40, 5), inputs then targets with the last axis packed 8 voxels
    to a byte (a 4,000-sequence set takes 0.8 GB instead of 6 GB); with ``registered`` a third
    channel, the surface earlier views saw (:func:`completion.evidence.registered_surfaces`, what
    a ``registered_input`` model takes); ``condition``: one name per
    sequence. The packed array is cached beside the shards (``.packed-*.npz``) so the next run
    starts in seconds; the cache is keyed by the name, size and modification time of every shard
    it holds, so regenerated shards are read again rather than taken from a stale cache.
    """
    paths = _shard_paths(folder, conditions, split)
    stamps = (f"{p.name} {p.stat().st_size} {p.stat().st_mtime_ns}" for p in paths)
    key = hashlib.sha1("\n".join(stamps).encode()).hexdigest()[:12]
    kind = "registered-" if registered else ""
    cache = folder / f".packed-{kind}{split}-{key}.npz"
    if cache.is_file():
        with np.load(cache, allow_pickle=False) as z:
            return {"packed": z["packed"], "condition": [str(c) for c in z["condition"]]}
    from tqdm import tqdm

    seqs = (load_sequence(p) for p in paths)
    packed, names = [], []
    for s in tqdm(seqs, total=len(paths), desc=f"load {split}", unit="seq", leave=False):
        channels = [s.inputs, s.targets]
        if registered:
            channels.append(registered_surfaces(s.inputs, s.grid_to_camera, s.camera_to_world))
        packed.append(np.packbits(np.stack(channels), axis=-1))
        names.append(s.meta["condition"])
    out = {"packed": np.stack(packed), "condition": names}
    tmp = cache.with_name(cache.name + ".tmp.npz")
    np.savez(tmp, packed=out["packed"], condition=np.array(names))
    tmp.replace(cache)
    return out


def _shard_paths(folder: Path, conditions: list[str], split: str) -> list[Path]:
    """The shards of ``conditions`` in ``folder``, in the order :func:`load_split` packs them."""
    paths = sorted(p for c in conditions for p in folder.glob(f"{c}_{split}_*.npz"))
    if not paths:
        raise ValueError(f"no {split} shards for {conditions} in {folder}")
    return paths


def unpack(packed: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, 2, L, 40, 40, 5) packed -> inputs, targets as float tensors (B, L, 40, 40, 40)."""
    grids = torch.from_numpy(np.unpackbits(packed[:, :2], axis=-1)).float()
    return grids[:, 0], grids[:, 1]


def unpack_seen(packed: np.ndarray) -> torch.Tensor | None:
    """The third channel of a ``registered`` split (B, L, 40, 40, 40) float; None without one."""
    if packed.shape[1] < 3:
        return None
    return torch.from_numpy(np.unpackbits(packed[:, 2], axis=-1)).float()


@torch.no_grad()
def validate(
    model: CompletionModel, val: dict, *, batch: int = 4, thresholds: tuple[float, ...] = THRESHOLDS
) -> dict:
    """Mean Jaccard over all views, per condition and threshold; also the mean over conditions."""
    model.eval()
    per_seq: dict[float, dict[str, list[float]]] = {t: {} for t in thresholds}
    for start in range(0, len(val["packed"]), batch):
        x, y = unpack(val["packed"][start : start + batch])
        seen = unpack_seen(val["packed"][start : start + batch])
        probs = torch.sigmoid(model(x) if seen is None else model(x, seen=seen))
        y = y.bool()
        for t in thresholds:
            jac = jaccard((probs >= t).numpy(), y.numpy()).mean(1)  # (B,) mean over views
            for k, cond in enumerate(val["condition"][start : start + batch]):
                per_seq[t].setdefault(cond, []).append(float(jac[k]))
    out = {}
    for t in thresholds:
        by_cond = {c: float(np.mean(v)) for c, v in sorted(per_seq[t].items())}
        out[f"{t:.2f}"] = {"per_condition": by_cond, "mean": float(np.mean(list(by_cond.values())))}
    model.train()
    return out


@torch.no_grad()
def per_view(path: Path, val_dir: Path, threshold: float | None = None) -> dict:
    """Validation Jaccard per view index and condition, with the model's memory and with every
    view fed alone (a sequence of one): what the memory adds, view by view."""
    model = load_checkpoint(path).eval()
    thr = float(threshold if threshold is not None else getattr(model, "threshold", 0.5))
    val = load_split(val_dir, list(CONDITIONS), "val")
    names = np.asarray(val["condition"])
    out = {}
    for condition in (c for c in CONDITIONS if c in set(names)):
        x, y = unpack(val["packed"][np.flatnonzero(names == condition)])
        b, n = x.shape[:2]
        alone = model(x.reshape(b * n, 1, *x.shape[2:])).reshape(x.shape)
        rows = {}
        for key, logits in (("with_memory", model(x)), ("views_alone", alone)):
            scores = jaccard((torch.sigmoid(logits) >= thr).numpy(), y.bool().numpy()).mean(0)
            rows[key] = np.round(scores, 4).tolist()
        out[condition] = rows
    return {"checkpoint": str(path), "threshold": thr, "per_view_jaccard": out}


def select_threshold(paths: list[Path], fixed: float | None = None) -> float:
    """Choose one decision threshold for every model: the one with the best validation Jaccard
    averaged over models and conditions (read from each checkpoint's stored sweep), or ``fixed``
    (one of the sweep's values, chosen on another criterion the model card gives), and write it
    into every checkpoint (its ``threshold`` entry, which :func:`load_model` applies)."""
    sweeps = [read_checkpoint(p)["val"] for p in paths]
    keys = sorted(set.intersection(*(set(s) for s in sweeps)))
    score = {k: float(np.mean([s[k]["mean"] for s in sweeps])) for k in keys}
    best = max(keys, key=lambda k: score[k])
    if fixed is not None:
        if f"{fixed:.2f}" not in score:
            raise ValueError(f"--threshold must be one of the sweep's values {keys}, got {fixed}")
        best = f"{fixed:.2f}"
    for p in paths:
        payload = read_checkpoint(p)
        payload["threshold"] = float(best)
        tmp = p.with_name(p.name + ".tmp")
        torch.save(payload, tmp)
        tmp.replace(p)
    print(json.dumps({"threshold": float(best), "mean_val_jaccard": score}), flush=True)
    return float(best)


def model_card(paths: list[Path]) -> str:
    """The model card (Markdown) of shipped checkpoints, from what each checkpoint recorded."""
    rows, cond_rows = [], []
    conditions = list(CONDITIONS)
    threshold = None
    for p in paths:
        ck = read_checkpoint(p)
        model = load_checkpoint(p)
        threshold = ck.get("threshold", 0.5)
        key = f"{float(threshold):.2f}"
        val = ck["val"].get(key, ck["val"]["0.50"])
        rows.append(
            f"| {p.stem} | {ck['config']['kind']} | {ck['views']} | {model.n_params():,} | "
            f"{ck['epoch']} | {ck['step']} | {ck['wall_s'] / 60:.1f} | {ck['device']} | "
            f"{val['mean']:.3f} | `{ck['command']}` |"
        )
        cond_rows.append(f"| {p.stem} | " + " | ".join(
            f"{val['per_condition'].get(c, float('nan')):.3f}" for c in conditions) + " |")
    return "\n".join([
        "| model | kind | train views | params | epochs | steps | wall (min) | device | "
        f"val Jaccard @ {threshold} | command |",
        "|---|---|---|---|---|---|---|---|---|---|", *rows, "",
        f"Validation Jaccard per condition (mean over 12 views, threshold {threshold}):", "",
        "| model | " + " | ".join(conditions) + " |",
        "|---|" + "---|" * len(conditions), *cond_rows,
    ])
