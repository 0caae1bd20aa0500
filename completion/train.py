"""Train a completion model on simulated sequences of the five conditions.

Example (the shipped MVP; see completion/weights/README.md for the exact runs)::

    python -m completion.train --model mvp --conditions all --minutes 8 \\
        --train-dir data/train --val-dir data/val --out completion/weights/mvp.pt

Shards are read from ``--train-dir`` / ``--val-dir``; sequences that are missing are generated
first (``--train-count`` / ``--val-count`` per condition, seed ``--data-seed``). Loss: binary
cross-entropy with logits and ``pos_weight``; Adam. After every epoch (and at the end) the model
is scored on the validation set (Jaccard per condition over all 12 views, at several thresholds);
the best checkpoint by mean Jaccard at 0.5 is written to ``--out`` (fp16 weights, loaded back to
fp32) with its figures; ``<run-dir>/last.pt`` holds the full training state for ``--resume``.
``--views 3`` / ``--views 6`` train on random windows of 3 / 6 consecutive views (MVP3 / MVP6).

One decision threshold for all models is then chosen on the validation sweeps::

    python -m completion.train select-threshold completion/weights/*.pt
"""

from __future__ import annotations

import argparse
import copy
import json
import random
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from completion.data import generate, load_sequence, parse_conditions
from completion.model import (
    DEFAULT_CONFIGS,
    CompletionModel,
    build_model,
    default_config,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
)
from completion.scenes import CONDITIONS

THRESHOLDS = tuple(round(x, 2) for x in np.arange(0.2, 0.81, 0.05))


def load_split(folder: Path, conditions: list[str], split: str) -> dict[str, torch.Tensor]:
    """Every shard of the given conditions in ``folder``: bool tensors (N, L, 40, 40, 40)."""
    paths = sorted(p for c in conditions for p in folder.glob(f"{c}_{split}_*.npz"))
    if not paths:
        raise ValueError(f"no {split} shards for {conditions} in {folder}")
    seqs = [load_sequence(p) for p in paths]
    return {
        "inputs": torch.from_numpy(np.stack([s.inputs for s in seqs])),
        "targets": torch.from_numpy(np.stack([s.targets for s in seqs])),
        "condition": [s.meta["condition"] for s in seqs],
    }


def ensure_data(
    folder: Path, split: str, conditions: list[str], count: int, seed: int, workers: int
) -> None:
    generate(conditions, split, count, seed=seed, out=folder, workers=workers)


@torch.no_grad()
def validate(
    model: CompletionModel, val: dict, *, batch: int = 8, thresholds: tuple[float, ...] = THRESHOLDS
) -> dict:
    """Mean Jaccard over all views, per condition and threshold; also the mean over conditions."""
    model.eval()
    per_seq: dict[float, dict[str, list[float]]] = {t: {} for t in thresholds}
    for start in range(0, len(val["inputs"]), batch):
        x = val["inputs"][start : start + batch].float()
        y = val["targets"][start : start + batch]
        probs = torch.sigmoid(model(x))
        for t in thresholds:
            pred = probs >= t
            i = (pred & y).flatten(2).sum(-1).float()
            u = (pred | y).flatten(2).sum(-1).float()
            jac = torch.where(u > 0, i / u.clamp(min=1), torch.ones_like(u)).mean(1)
            for k, cond in enumerate(val["condition"][start : start + batch]):
                per_seq[t].setdefault(cond, []).append(float(jac[k]))
    out = {}
    for t in thresholds:
        by_cond = {c: float(np.mean(v)) for c, v in sorted(per_seq[t].items())}
        out[f"{t:.2f}"] = {"per_condition": by_cond, "mean": float(np.mean(list(by_cond.values())))}
    model.train()
    return out


def train(args: argparse.Namespace) -> dict:
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)
    random.seed(args.seed)
    torch.set_num_threads(args.threads)
    device = torch.device(
        ("cuda" if torch.cuda.is_available() else "cpu") if args.device == "auto" else args.device
    )
    conditions = args.conditions
    if args.train_count:
        ensure_data(
            args.train_dir, "train", conditions, args.train_count, args.data_seed, args.workers
        )
    if args.val_count:
        ensure_data(args.val_dir, "val", conditions, args.val_count, args.data_seed, args.workers)
    train_set = load_split(args.train_dir, conditions, "train")
    val_set = load_split(args.val_dir, conditions, "val")
    n_train, full_views = train_set["inputs"].shape[:2]
    if args.views > full_views:
        raise ValueError(f"--views {args.views} exceeds the {full_views} views in the shards")
    print(f"train: {n_train} sequences, val: {len(val_set['inputs'])}, device {device}", flush=True)

    config = default_config(args.model, **args.config, seed=args.seed)
    model = build_model(config).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    run_dir = args.run_dir or Path("runs") / args.out.stem
    run_dir.mkdir(parents=True, exist_ok=True)
    last = run_dir / "last.pt"
    step, epoch, best, history, elapsed_before = 0, 0, -1.0, [], 0.0
    if args.resume and last.is_file():
        payload = read_checkpoint(last)
        model.load_state_dict(payload["state_dict"])
        opt.load_state_dict(payload["optimizer"])
        step, epoch = payload["step"], payload["epoch"]
        best, history = payload["best"], payload["history"]
        elapsed_before = payload["wall_s"]
        print(f"resumed from {last} at epoch {epoch}, step {step}", flush=True)

    from tqdm import tqdm

    gen = torch.Generator().manual_seed(args.seed + epoch)
    pos_weight = torch.tensor(args.pos_weight, device=device)
    tic = time.perf_counter()
    budget_s = args.minutes * 60 if args.minutes else float("inf")
    done = False
    skipped = 0
    while epoch < args.epochs and not done:
        order = torch.randperm(n_train, generator=gen)
        bar = tqdm(
            range(0, n_train - args.batch_size + 1, args.batch_size),
            desc=f"{args.model} epoch {epoch}",
            unit="batch",
            disable=args.quiet,
        )
        for start in bar:
            idx = order[start : start + args.batch_size]
            first = int(torch.randint(0, full_views - args.views + 1, (1,), generator=gen))
            x = train_set["inputs"][idx, first : first + args.views].to(device).float()
            y = train_set["targets"][idx, first : first + args.views].to(device).float()
            loss = F.binary_cross_entropy_with_logits(model(x), y, pos_weight=pos_weight)
            opt.zero_grad(set_to_none=True)
            if not torch.isfinite(loss):
                skipped += 1  # never let one bad batch poison the weights
                continue
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), args.clip)
            opt.step()
            step += 1
            bar.set_postfix(loss=f"{loss.item():.4f}")
            if time.perf_counter() - tic > budget_s:
                done = True
                break
        epoch += 1
        scores = validate(model, val_set)
        mean = scores["0.50"]["mean"]
        history.append(
            {"epoch": epoch, "step": step, "val_jaccard": mean, "loss": float(loss.item()),
             "skipped": skipped}
        )
        wall = elapsed_before + time.perf_counter() - tic
        print(
            f"epoch {epoch} step {step} loss {loss.item():.4f} val Jaccard {mean:.4f} "
            f"({wall / 60:.1f} min)",
            flush=True,
        )
        if mean > best:
            best = mean
            save_checkpoint(
                copy.deepcopy(model).half().cpu(),
                args.out,
                name=args.out.stem,
                threshold=0.5,
                views=args.views,
                conditions=conditions,
                val=scores,
                epoch=epoch,
                step=step,
                wall_s=wall,
                device=str(device),
                train_sequences=n_train,
                command=args.command,
            )
        save_checkpoint(
            model,
            last,
            optimizer=opt.state_dict(),
            step=step,
            epoch=epoch,
            best=best,
            history=history,
            wall_s=wall,
        )
    wall = elapsed_before + time.perf_counter() - tic
    summary = {
        "out": str(args.out),
        "best_val_jaccard": best,
        "epochs": epoch,
        "steps": step,
        "wall_s": round(wall, 1),
        "params": model.n_params(),
        "history": history,
    }
    print(json.dumps(summary), flush=True)
    return summary


def select_threshold(paths: list[Path]) -> float:
    """Choose one decision threshold for every model: the one with the best validation Jaccard
    averaged over models and conditions (read from each checkpoint's stored sweep), and write it
    into every checkpoint (its ``threshold`` entry, which :func:`load_model` applies)."""
    sweeps = [read_checkpoint(p)["val"] for p in paths]
    keys = sorted(set.intersection(*(set(s) for s in sweeps)))
    score = {k: float(np.mean([s[k]["mean"] for s in sweeps])) for k in keys}
    best = max(keys, key=lambda k: score[k])
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


def _overrides(text: str) -> dict:
    """``key=value,key=value`` ModelConfig overrides; tuples as ``channels=8:16:32``."""
    out: dict = {}
    for item in filter(None, text.split(",")):
        key, sep, value = item.partition("=")
        if not sep:
            raise argparse.ArgumentTypeError(f"expected key=value, got {item!r}")
        if ":" in value:
            out[key] = tuple(int(v) for v in value.split(":"))
        else:
            try:
                out[key] = int(value)
            except ValueError:
                try:
                    out[key] = float(value)
                except ValueError:
                    out[key] = value
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["select-threshold"]:
        paths = [Path(a) for a in argv[1:]]
        missing = [str(a) for a in paths if not a.is_file()]
        if not paths or missing:
            print("usage: python -m completion.train select-threshold CKPT [CKPT …] "
                  f"(checkpoint files; missing: {missing})", file=sys.stderr)
            return 2
        select_threshold(paths)
        return 0
    if argv[:1] == ["model-card"]:
        print(model_card([Path(a) for a in argv[1:]]))
        return 0
    p = argparse.ArgumentParser(
        prog="python -m completion.train",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--model", choices=sorted(DEFAULT_CONFIGS), required=True)
    p.add_argument("--conditions", type=parse_conditions, default=list(CONDITIONS))
    p.add_argument("--views", type=int, default=12, help="views per training window (3, 6, 12)")
    p.add_argument("--train-dir", type=Path, default=Path("data/train"))
    p.add_argument("--val-dir", type=Path, default=Path("data/val"))
    p.add_argument(
        "--train-count",
        type=int,
        default=200,
        help="sequences per condition to have in --train-dir (generated if missing; "
        "0 = use what is there)",
    )
    p.add_argument("--val-count", type=int, default=24)
    p.add_argument("--data-seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2, help="processes for data generation")
    p.add_argument("--epochs", type=int, default=100)
    p.add_argument("--minutes", type=float, default=8.0, help="wall-time budget (0 = none)")
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--pos-weight", type=float, default=2.0)
    p.add_argument("--clip", type=float, default=1.0, help="gradient norm clip")
    p.add_argument(
        "--config",
        type=_overrides,
        default={},
        help="ModelConfig overrides, e.g. embed_dim=256,channels=16:32:64",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto", help="auto, cpu or cuda")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", type=Path, required=True, help="best checkpoint path")
    p.add_argument("--run-dir", type=Path, default=None)
    p.add_argument("--resume", action="store_true")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    if args.views < 1:
        p.error(f"--views must be ≥ 1, got {args.views}")
    args.command = "python -m completion.train " + shlex.join(argv)
    train(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
