"""Train a completion model on simulated sequences of the five conditions.

Example (``completion/weights/recipe.sh`` is the exact chain behind the shipped weights)::

    python -m completion.train --model single_view --steps 1500 --out runs/single_view.pt
    python -m completion.train --model mvp --steps 1000 \\
        --init-from runs/single_view.pt --out runs/mvp.pt

``--model X`` alone builds the shipped architecture of X
(:data:`completion.config.DEFAULT_CONFIGS`).
Shards are read from ``--train-dir`` / ``--val-dir``; sequences that are missing are generated
first (``--train-count`` per condition with seed ``--data-seed`` for training, ``--val-count``
with seed 0 for validation). Loss: binary cross-entropy with logits and ``pos_weight``, plus
``--jaccard-weight`` × (1 − soft Jaccard) per view when asked (the evaluation's metric is the
Jaccard of each view, which BCE weighs by object size instead), the views weighed alike or,
with ``--late-weight``, more the later they come; Adam with a cosine decay over ``--steps`` (the
budget: the same command repeats the same run); ``--minutes`` only caps the wall time. Each step
draws ``--batch-size`` sequences (a window of ``--views`` consecutive views) and mirrors or
rolls each in the camera's x and y axes (``--augment``). The memory's options (``--blank-local``,
``--hide-views``, ``--hide-context``) blank views from one tower or both so that the memory must
carry the shape. Every ``--val-every`` steps and at the end the model is scored on the
validation set (:mod:`completion.validation`); the best checkpoint by mean Jaccard at 0.5 is
written to ``--out`` (fp16 weights, loaded back to fp32) with its figures (with ``--ema``, a
moving average of the weights is what is validated and written), and ``<run-dir>/last.pt``
(default: a folder beside ``--out`` named after it) holds the full training state for
``--resume``. ``--init-from`` starts from another checkpoint (:func:`warm_start`).

Subcommands (:mod:`completion.validation`)::

    python -m completion.train select-threshold completion/weights/*.pt   # one threshold for all
    python -m completion.train select-threshold --threshold 0.5 completion/weights/*.pt  # given
    python -m completion.train per-view completion/weights/mvp.pt data/val  # what the memory adds
    python -m completion.train model-card completion/weights/*.pt          # the card's tables
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import random
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from completion import train_args
from completion.config import ModelConfig, default_config
from completion.data import generate
from completion.distributed import World, setup
from completion.model import (
    CompletionModel,
    build_model,
    read_checkpoint,
    save_checkpoint,
    widened_inputs,
)
from completion.train_args import AUGMENTATIONS
from completion.train_args import _overrides as _overrides  # re-exported: callers import it here
from completion.validation import (
    load_split,
    model_card,
    per_view,
    select_threshold,
    unpack,
    unpack_seen,
)
from completion.validation import validate as validate_model


def draw_batch(n: int, size: int, gen: torch.Generator) -> np.ndarray:
    """``size`` sequence indices in [0, n), sorted, drawn uniformly with replacement."""
    return torch.randint(0, n, (size,), generator=gen).sort().values.numpy()


def augment(x: torch.Tensor, y: torch.Tensor, gen: torch.Generator, mode: str = "mirror",
            seen: torch.Tensor | None = None):
    """Random symmetries of the camera frame, per sequence, all views alike; never a flip of z,
    the viewing direction, which decides what is seen and what is hidden.

    ``mirror``: flip x and/or y (grid axes i, j). ``roll``: flip both or neither, a 180° roll
    about the viewing axis: a proper rotation, so the sense in which the camera circles the
    object is kept (a mirror reverses it, which rotary values cannot follow). ``seen`` (what
    earlier posed views saw, in each view's grid) turns with the inputs and is returned third;
    None stays None.
    """
    if mode not in AUGMENTATIONS:
        raise ValueError(f"augmentation must be one of {AUGMENTATIONS}, got {mode!r}")
    if mode == "none":
        return x, y, seen
    flips = torch.randint(0, 2, (len(x), 2 if mode == "mirror" else 1), generator=gen)
    for b, picks in enumerate(flips.tolist()):
        fx, fy = picks if mode == "mirror" else picks * 2
        dims = [d for d, f in ((1, fx), (2, fy)) if f]  # axes of one (L, G, G, G) sequence
        if dims:
            x[b], y[b] = x[b].flip(dims), y[b].flip(dims)
            if seen is not None:
                seen[b] = seen[b].flip(dims)
    return x, y, seen


def warm_start(model: CompletionModel, path: Path) -> list[str]:
    """Start from trained weights; returns the names of the tensors that kept their fresh init.

    A checkpoint of the same kind and shape loads whole (a new run that fine-tunes it, with its
    own schedule; rotary values may be switched on or off, they have no weights). Otherwise
    every tensor that both models have, by name and shape, loads: a Single-View U-Net gives a
    multi-view model both towers' encoders and the decoder; a multi-view model gives Single-View
    its local tower and decoder, and another multi-view kind its towers, decoder, bridge and
    whatever of its sequence block matches (MVT takes MVP's attention weights; an LSTM none).
    Unless the sequence block loaded whole, the context path's output layer then starts at zero,
    so the model begins exactly as the checkpoint's model without its memory and learns what
    its own memory adds. A model with more input channels (``registered_input``) takes the
    checkpoint's convolutions on the raw input for the first channel and zeros for the new one,
    so it begins exactly as the checkpoint's model and learns what the new input adds.
    """
    payload = read_checkpoint(path)
    weights = {k: v.float() for k, v in payload["state_dict"].items()}
    saved = ModelConfig.from_dict(payload["config"])
    same = {"seed": model.config.seed, "value_rotation": model.config.value_rotation}
    if saved.replace(**same) == model.config:
        model.load_state_dict(weights)
        return []
    if saved.kind == "single_view" and model.context_encoder is not None:
        # one U-Net for both towers: the context encoder starts as the local one
        weights.update({"context_" + k: v for k, v in weights.items() if k.startswith("encoder.")})
    own = model.state_dict()
    taken = {k: v for k, v in weights.items() if k in own and own[k].shape == v.shape}
    taken |= {k: wide for k, v in weights.items() if k in own and k not in taken
              and (wide := widened_inputs(v, own[k])) is not None}
    if not any(k.startswith("encoder.") for k in taken):
        raise ValueError(f"--init-from: {path} ({saved.kind}) shares no U-Net with this model "
                         f"({model.config.kind}): a checkpoint of the same grid and channels")
    model.load_state_dict(taken, strict=False)
    fresh = [k for k in own if k not in taken]
    if any(k.startswith("tower.") for k in fresh):
        with torch.no_grad():
            for p in model.bridge.expand.parameters():
                p.zero_()
    return fresh


def mask_views(
    x: torch.Tensor,
    gen: torch.Generator,
    *,
    hide: float = 0.0,
    blank_local: float = 0.0,
    hide_context: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Training-time view masking of a batch ``x`` (B, L, G, G, G); the targets never change.

    ``hide``: each view after the first becomes empty for both towers with this probability, so
    only the memory of earlier views can say what it holds (``--hide-views``). ``blank_local``:
    each view becomes empty for the local tower alone, the context tower still sees it
    (``--blank-local``). ``hide_context``: each view after the first becomes empty for the context
    tower alone, the local tower still sees it, so the memory's part of that view must come from
    earlier views and be merged with what the current one shows (``--hide-context``). Returns
    (what the context tower sees, what the local tower sees or None for the same). Draws from
    ``gen`` only for the options that are on, so runs without them keep their random stream.
    """
    def later_views(p: float) -> torch.Tensor:  # (B, L, 1, 1, 1): drawn, never the first view
        drawn = torch.rand(x.shape[:2], generator=gen) < p
        drawn[:, 0] = False  # the first view has no memory to draw on
        return drawn[..., None, None, None]

    if hide:
        x = x * ~later_views(hide)
    local = None
    if blank_local:
        keep = torch.rand(x.shape[:2], generator=gen) >= blank_local
        local = x * keep[..., None, None, None]
    if hide_context:
        local = x if local is None else local
        x = x * ~later_views(hide_context)
    return x, local


def soft_jaccard_loss(
    logits: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None = None
) -> torch.Tensor:
    """Mean over views of 1 − soft Jaccard (probabilities for the prediction, one voxel of
    smoothing); ``logits`` and ``target`` are (..., D, H, W) with one view per leading index,
    ``weights`` (broadcast over the leading indices) weighs the views' terms.
    On binary predictions it is 1 − the Jaccard the evaluation scores."""
    p = torch.sigmoid(logits).flatten(-3)
    t = target.flatten(-3)
    inter = (p * t).sum(-1)
    union = p.sum(-1) + t.sum(-1) - inter
    per_view = 1 - (inter + 1) / (union + 1)
    return (per_view if weights is None else per_view * weights).mean()


def view_weights(views: int, late: float) -> torch.Tensor:
    """(views,) loss weights rising linearly from the first view to the last, ``late`` times the
    first's, normalised to mean 1 (``--late-weight``; 1 = every view alike). In a pan the views
    are alike for the local tower (the start angle is random), so what a later view gains over an
    earlier one comes from the memory: the tilt weighs the memory's part of the gradient."""
    if views == 1:
        return torch.ones(1)
    ramp = 1 + (late - 1) * torch.arange(views, dtype=torch.float32) / (views - 1)
    return ramp / ramp.mean()


def run_config(args: argparse.Namespace) -> ModelConfig:
    """The architecture a run trains: the shipped one of ``--model``, with ``--config``'s
    changes, initialised from ``--seed``."""
    return default_config(args.model, **args.config, seed=args.seed)


def train(args: argparse.Namespace) -> dict:
    """One training run; under torchrun each rank trains on its own part of the data."""
    world, device = setup(args.device)
    try:
        summary = _train(args, world, device)
    except BaseException:
        world.close(wait=False)
        raise
    world.close()
    return summary


@dataclass
class _Run:
    """One run's state, shared by the phases of :func:`_train` (setup, steps, checkpoints) so
    that each phase takes one object instead of a dozen arguments."""

    args: argparse.Namespace
    world: World
    device: torch.device
    train_set: dict
    val_set: dict | None
    part: np.ndarray  # the training sequences this rank draws from
    model: CompletionModel
    net: torch.nn.Module  # what the steps call: the model, or DDP around it
    opt: torch.optim.Optimizer
    ema: torch.nn.Module | None
    last: Path  # the full training state, for --resume
    gen: torch.Generator  # this rank's sampler
    step: int = 0
    best: float = -1.0
    history: list = field(default_factory=list)
    elapsed_before: float = 0.0  # wall time of the runs this one resumes
    skipped: int = 0
    tic: float = 0.0
    loss: torch.Tensor = field(default_factory=lambda: torch.zeros(()))

    def wall(self) -> float:
        return self.elapsed_before + time.perf_counter() - self.tic

    def checkpoint(self) -> None:
        """Rank 0 validates and writes; every rank hands it its sampler state first."""
        args, world = self.args, self.world
        n_all = len(self.train_set["packed"])
        generators = world.gather(self.gen.get_state())
        if world.main:
            self.best = _validate_and_save(
                args, self.model, self.ema, self.opt, self.val_set, generators, self.last,
                step=self.step, best=self.best, history=self.history, wall_s=self.wall(),
                skipped=self.skipped, loss=self.loss, n_train=n_all, device=self.device,
                epochs=self.step * args.batch_size * world.size / n_all, world=world,
            )
        world.barrier()


def _train(args: argparse.Namespace, world: World, device: torch.device) -> dict:
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)
    random.seed(args.seed)
    torch.set_num_threads(args.threads)
    train_set, val_set, part = _load_data(args, world, device)
    model, net, opt, ema = _build(args, world, device)
    run_dir = args.run_dir or args.out.with_suffix("")  # beside --out, never the working dir
    run_dir.mkdir(parents=True, exist_ok=True)
    gen = torch.Generator().manual_seed(args.seed + 1_000_003 * world.rank)
    run = _Run(args, world, device, train_set, val_set, part, model, net, opt, ema,
               last=run_dir / "last.pt", gen=gen)
    if args.resume and run.last.is_file():
        _resume(run)
    _steps(run)
    if not run.history or run.history[-1]["step"] != run.step:
        run.checkpoint()
    summary = {
        "out": str(args.out),
        "best_val_jaccard": run.best,
        "steps": run.step,
        "wall_s": round(run.wall(), 1),
        "params": model.n_params(),
        "history": run.history,
        "ranks": world.size,
    }
    if world.main:
        print(json.dumps(summary), flush=True)
    return summary


def _load_data(args: argparse.Namespace, world: World, device: torch.device):
    """The training split (every rank), the validation split (rank 0, else None) and the
    training sequences this rank draws from; rank 0 first generates the missing shards."""
    conditions = args.conditions
    registered = run_config(args).registered_input  # a third channel: what earlier views saw
    if world.main:  # one rank generates missing shards and writes the packed caches
        if args.train_count:
            generate(conditions, "train", args.train_count, seed=args.data_seed,
                     out=args.train_dir, workers=args.workers)
        if args.val_count:
            generate(conditions, "val", args.val_count, seed=0, out=args.val_dir,
                     workers=args.workers)
        train_set = load_split(args.train_dir, conditions, "train", registered=registered)
    world.barrier()
    if not world.main:  # from the packed cache rank 0 wrote
        train_set = load_split(args.train_dir, conditions, "train", registered=registered)
    val_set = (load_split(args.val_dir, conditions, "val", registered=registered)
               if world.main else None)
    n_all, _, full_views = train_set["packed"].shape[:3]
    # each rank draws from its own part of the training sequences (all of them on one process)
    part = np.arange(world.rank, n_all, world.size)
    n_train = len(part)
    if args.views > full_views:
        raise ValueError(f"--views {args.views} exceeds the {full_views} views in the shards")
    if args.batch_size > n_train:
        raise ValueError(f"--batch-size {args.batch_size} exceeds the {n_train} sequences")
    if world.main:
        ranks = f", {world.size} ranks × {n_train}" if world.distributed else ""
        print(f"train: {n_all} sequences{ranks}, val: {len(val_set['packed'])}, device {device}",
              flush=True)  # fmt: skip
    return train_set, val_set, part


def _build(args: argparse.Namespace, world: World, device: torch.device):
    """The model (warm-started with ``--init-from``) on ``device``, what the steps call (DDP
    around it on several ranks), its optimizer and, with ``--ema``, its weight average."""
    model = build_model(run_config(args))
    if args.init_from:
        fresh = warm_start(model, args.init_from)
        if world.main and fresh:
            print(f"--init-from {args.init_from}: {len(fresh)} tensors keep their fresh init: "
                  f"{', '.join(fresh)}", flush=True)
    model = model.to(device)
    net = model  # what the steps call: DDP averages the gradients over the ranks
    if world.distributed:
        net = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None
        )
    params = [{"params": list(model.parameters()), "base_lr": args.lr}]  # base_lr: the schedule's
    opt = torch.optim.Adam(params, lr=args.lr)
    # an exponential moving average of the weights, when asked: what is validated and shipped
    ema = None
    if args.ema:
        from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

        ema = AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(args.ema), use_buffers=True)
    return model, net, opt, ema


def _resume(run: _Run) -> None:
    """Continue ``run.last``: weights, optimizer, this rank's sampler, weight average, counters."""
    world, last, opt = run.world, run.last, run.opt
    payload = read_checkpoint(last)
    run.model.load_state_dict(payload["state_dict"])
    base_lrs = [group["base_lr"] for group in opt.param_groups]
    opt.load_state_dict(payload["optimizer"])  # its groups may predate base_lr
    for group, base_lr in zip(opt.param_groups, base_lrs, strict=True):
        group["base_lr"] = base_lr
    generators = payload.get("generators") or [payload["generator"]]
    if len(generators) != world.size:
        raise ValueError(f"{last} was written by {len(generators)} rank(s); resume it with "
                         f"the same number, not {world.size}")
    run.gen.set_state(generators[world.rank])
    if run.ema is not None:
        if "ema" not in payload:
            raise ValueError(f"{last} has no weight average; resume it without --ema")
        run.ema.load_state_dict(payload["ema"])
    run.step, run.best, run.history = payload["step"], payload["best"], payload["history"]
    run.elapsed_before, run.skipped = payload["wall_s"], payload["skipped"]
    if world.main:
        print(f"resumed from {last} at step {run.step}", flush=True)


def _steps(run: _Run) -> None:
    """The optimizer steps up to ``--steps`` (or ``--minutes``), validating every
    ``--val-every``; a non-finite loss on any rank skips its step on every rank."""
    from tqdm import tqdm

    args, world, model, opt = run.args, run.world, run.model, run.opt
    pos_weight = torch.tensor(args.pos_weight, device=run.device)
    # per-view loss weights along the sequence; None: the plain mean (the runs before the option)
    weights = None
    if args.late_weight != 1:
        weights = view_weights(args.views, args.late_weight).to(run.device)
    run.tic = time.perf_counter()
    budget_s = args.minutes * 60 if args.minutes else float("inf")
    autocast = torch.autocast(run.device.type, dtype=torch.bfloat16,
                              enabled=args.precision == "bf16")
    bar = tqdm(total=args.steps, initial=run.step, desc=args.model, unit="step",
               disable=args.quiet or not world.main)  # fmt: skip
    model.train()
    full_views = run.train_set["packed"].shape[2]
    while run.step < args.steps:
        if run.wall() - run.elapsed_before > budget_s:
            print(f"stopping at step {run.step}: --minutes {args.minutes} reached", flush=True)
            break
        x, y, local, seen = _batch(run.train_set["packed"], run.part, full_views, args, run.gen,
                                   run.device)
        decay = 0.1 + 0.45 * (1 + math.cos(math.pi * run.step / args.steps))  # to a tenth
        for group in opt.param_groups:  # cosine decay over the step budget
            group["lr"] = group["base_lr"] * decay
        with autocast:
            logits = run.net(x, local=local, seen=seen)
        run.loss = loss = _loss(args, logits, y, pos_weight, weights)
        opt.zero_grad(set_to_none=True)
        run.step += 1
        bar.update()
        if not world.all_true(bool(torch.isfinite(loss))):
            run.skipped += 1  # never let one bad batch poison the weights (on any rank)
        else:
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), args.clip)
            opt.step()
            if run.ema is not None:
                run.ema.update_parameters(model)
            bar.set_postfix(loss=f"{loss.item():.4f}")
        if run.step % args.val_every == 0 and run.step < args.steps:
            run.checkpoint()
    bar.close()


def _loss(args: argparse.Namespace, logits: torch.Tensor, y: torch.Tensor,
          pos_weight: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
    """BCE with ``pos_weight`` (the per-view mean weighed by ``weights`` along the sequence, if
    any), plus ``--jaccard-weight`` × the soft Jaccard loss."""
    if weights is None:
        loss = F.binary_cross_entropy_with_logits(logits.float(), y, pos_weight=pos_weight)
    else:  # the per-view mean weighed along the sequence
        loss = F.binary_cross_entropy_with_logits(logits.float(), y, pos_weight=pos_weight,
                                                  reduction="none")
        loss = (loss.mean((-3, -2, -1)) * weights).mean()
    if args.jaccard_weight:
        loss = loss + args.jaccard_weight * soft_jaccard_loss(logits.float(), y, weights)
    return loss


def _batch(packed: np.ndarray, part: np.ndarray, full_views: int, args: argparse.Namespace,
           gen: torch.Generator, device: torch.device):
    """A step's window of ``--views`` from sequences ``part``, augmented and masked, on ``device``:
    (inputs, targets, the local tower's or None, what earlier posed views saw or None)."""
    idx = part[draw_batch(len(part), args.batch_size, gen)]
    first = int(torch.randint(0, full_views - args.views + 1, (1,), generator=gen))
    window = packed[idx, :, first : first + args.views]
    x, y = unpack(window)
    x, y, seen = augment(x, y, gen, args.augment, unpack_seen(window))
    x, local = mask_views(x, gen, hide=args.hide_views, blank_local=args.blank_local,
                          hide_context=args.hide_context)
    return tuple(None if t is None else t.to(device) for t in (x, y, local, seen))


def _validate_and_save(args, model, ema, opt, val_set, generators, last, *, step, best, history,
                       wall_s, skipped, loss, epochs, n_train, device, world) -> float:
    """Score the model (its weight average with ``--ema``) on the validation set, write the best
    checkpoint (``args.out``) and the full training state (``last``); returns the best mean
    validation Jaccard so far."""
    scored = model if ema is None else ema.module
    scores = validate_model(scored, val_set)
    mean = scores["0.50"]["mean"]
    last_loss = float(loss.detach())
    history.append({"step": step, "epochs": round(epochs, 3), "val_jaccard": mean,
                    "loss": last_loss, "skipped": skipped, "wall_s": round(wall_s, 1)})
    print(f"step {step} ({epochs:.2f} epochs) loss {last_loss:.4f} val Jaccard {mean:.4f} "
          f"({wall_s / 60:.1f} min)", flush=True)
    if mean > best:
        best = mean
        save_checkpoint(
            copy.deepcopy(scored).half().cpu(), args.out, name=args.out.stem, threshold=0.5,
            views=args.views, conditions=args.conditions, val=scores, epoch=round(epochs, 3),
            step=step, wall_s=wall_s, device=str(device), train_sequences=n_train,
            precision=args.precision, init_from=str(args.init_from or ""),
            command=args.command, ranks=world.size,
        )
    averaged = {} if ema is None else {"ema": ema.state_dict()}
    save_checkpoint(model, last, optimizer=opt.state_dict(), **averaged,
                    generator=generators[0], generators=generators, step=step, best=best,
                    history=history, wall_s=wall_s, skipped=skipped)
    return best


def parse_args(argv: list[str]) -> argparse.Namespace:
    """The training command's options, checked (:mod:`completion.train_args`; files named by
    them are checked by :func:`main`, so a recipe can be checked before its checkpoints exist)."""
    return train_args.parse_args(argv, description=__doc__)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["select-threshold"]:
        fixed, rest = None, argv[1:]
        if rest[:1] == ["--threshold"]:
            try:
                fixed, rest = float(rest[1]), rest[2:]
            except (IndexError, ValueError):
                fixed, rest = float("nan"), []
        paths = [Path(a) for a in rest]
        missing = [str(a) for a in paths if not a.is_file()]
        if not paths or missing:
            print("usage: python -m completion.train select-threshold [--threshold T] CKPT "
                  f"[CKPT …] (checkpoint files; missing: {missing}; T: one of the validation "
                  "sweep's thresholds, default: the best mean validation Jaccard)",
                  file=sys.stderr)
            return 2
        try:
            select_threshold(paths, fixed)
        except ValueError as error:
            print(f"select-threshold: {error}", file=sys.stderr)
            return 2
        return 0
    if argv[:1] == ["per-view"]:
        if len(argv) not in (2, 3) or not Path(argv[1]).is_file():
            print("usage: python -m completion.train per-view CKPT [VAL_DIR] (a checkpoint "
                  "file; validation shards, default data/val)", file=sys.stderr)
            return 2
        print(json.dumps(per_view(Path(argv[1]), Path(argv[2] if len(argv) == 3 else "data/val"))))
        return 0
    if argv[:1] == ["model-card"]:
        paths = [Path(a) for a in argv[1:]]
        if not paths or not all(p.is_file() for p in paths):
            print("usage: python -m completion.train model-card CKPT [CKPT …] (checkpoint files)",
                  file=sys.stderr)
            return 2
        print(model_card(paths))
        return 0
    args = parse_args(argv)
    if args.init_from and not args.init_from.is_file():
        print(f"python -m completion.train: error: --init-from: no such checkpoint "
              f"{args.init_from}", file=sys.stderr)
        return 2
    train(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
