"""The command line of ``python -m completion.train``: its options, group by group, and the checks
on them. Kept apart from :mod:`completion.train` so that module holds the training alone; its
:func:`completion.train.parse_args` is the entry point (it passes the module's docstring as the
description)."""

from __future__ import annotations

import argparse
import math
import shlex
from pathlib import Path

from completion.cli import DefaultsAndRawDescription, one_name
from completion.config import DEFAULT_CONFIGS, default_config
from completion.data import parse_conditions
from completion.scenes import CONDITIONS

AUGMENTATIONS = ("mirror", "roll", "none")


def _overrides(text: str) -> dict:
    """``key=value,key=value`` ModelConfig overrides; tuples as ``channels=8:16:32``, booleans
    as ``qk_norm=true``."""
    out: dict = {}
    for item in filter(None, text.split(",")):
        key, sep, value = item.partition("=")
        if not sep:
            raise argparse.ArgumentTypeError(f"expected key=value, got {item!r}")
        if ":" in value:
            out[key] = tuple(int(v) for v in value.split(":"))
        elif value.lower() in ("true", "false"):
            out[key] = value.lower() == "true"
        else:
            try:
                out[key] = int(value)
            except ValueError:
                try:
                    out[key] = float(value)
                except ValueError:
                    out[key] = value
    return out


def _add_data_options(p: argparse.ArgumentParser) -> None:
    """What is trained on what: the model, and the shards (generated first where missing)."""
    p.add_argument("--model", type=one_name(tuple(sorted(DEFAULT_CONFIGS)), "models"),
                   required=True, help=f"one of {', '.join(sorted(DEFAULT_CONFIGS))}")
    p.add_argument("--conditions", type=parse_conditions, default=list(CONDITIONS))
    p.add_argument("--views", type=int, default=12, help="views per training window (3, 6, 12)")
    p.add_argument("--train-dir", type=Path, default=Path("data/train"))
    p.add_argument("--val-dir", type=Path, default=Path("data/val"))
    p.add_argument("--train-count", type=int, default=800,
                   help="sequences per condition to have in --train-dir (generated if missing; "
                   "0 = use what is there)")
    p.add_argument("--val-count", type=int, default=24)
    p.add_argument("--data-seed", type=int, default=1,
                   help="seed of the training shards (the evaluation draws seed 0)")
    p.add_argument("--workers", type=int, default=2, help="processes for data generation")


def _add_schedule_options(p: argparse.ArgumentParser) -> None:
    """The budget, the optimizer and the loss."""
    p.add_argument("--steps", type=int, default=1000,
                   help="optimizer steps (the budget; the learning rate decays over it)")
    p.add_argument("--minutes", type=float, default=0.0,
                   help="wall-time cap in minutes on top of --steps (0 = none)")
    p.add_argument("--val-every", type=int, default=250, help="validate every N steps")
    p.add_argument("--batch-size", type=int, default=2, help="sequences per step")
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--pos-weight", type=float, default=2.0)
    p.add_argument("--jaccard-weight", type=float, default=0.0, metavar="W",
                   help="add W × (1 − soft Jaccard per view) to the loss (0: BCE alone)")
    p.add_argument("--ema", type=float, default=0.0, metavar="DECAY",
                   help="validate and ship an exponential moving average of the weights with "
                        "this decay per step, e.g. 0.999 (0: the raw weights)")
    p.add_argument("--clip", type=float, default=1.0, help="gradient norm clip")


def _add_run_options(p: argparse.ArgumentParser) -> None:
    """The architecture's changes, the seed and the machine, and where the run starts and ends."""
    p.add_argument("--config", type=_overrides, default={},
                   help="ModelConfig overrides, e.g. embed_dim=128,channels=8:16:32")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto", help="auto, cpu or cuda")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", type=Path, required=True, help="best checkpoint path")
    p.add_argument("--run-dir", type=Path, default=None,
                   help="where last.pt (the state --resume continues) goes; default: --out "
                   "without its suffix (runs/mvp.pt -> runs/mvp/)")
    p.add_argument("--resume", action="store_true", help="continue <run-dir>/last.pt")
    p.add_argument("--init-from", type=Path, default=None,
                   help="start from a checkpoint: the same model whole, or every tensor another "
                   "kind shares with it (a Single-View U-Net, a multi-view model's towers); "
                   "default: random initialisation")
    p.add_argument("--precision", choices=("fp32", "bf16"), default="fp32",
                   help="bf16 autocast for the convolutions (fp32 master weights)")


def _add_view_options(p: argparse.ArgumentParser) -> None:
    """What each training sequence undergoes: its symmetries, the views hidden from one tower or
    both, and the weight of each view's loss."""
    p.add_argument("--augment", choices=AUGMENTATIONS, default="mirror",
                   help="random symmetry of each training sequence: mirror (x and/or y), roll "
                   "(x and y together: keeps the sense of a camera pan) or none")
    p.add_argument("--no-augment", dest="augment", action="store_const", const="none",
                   help="same as --augment none")
    p.add_argument("--blank-local", type=float, default=0.0, metavar="P",
                   help="multi-view models: hide each training view from the local tower with "
                   "probability P (the context tower still sees it), so that the memory path "
                   "learns to carry the shape; 0 = off")
    p.add_argument("--hide-views", type=float, default=0.0, metavar="P",
                   help="multi-view models: blank each training view after the first from both "
                   "towers with probability P (the target stays), so that the memory must carry "
                   "earlier views' shape into the current view's frame; 0 = off")
    p.add_argument("--hide-context", type=float, default=0.0, metavar="P",
                   help="multi-view models: blank each training view after the first from the "
                   "context tower alone with probability P (the local tower still sees it), so "
                   "that the memory of earlier views must be merged with the current view; "
                   "0 = off")
    p.add_argument("--late-weight", type=float, default=1.0, metavar="W",
                   help="multi-view models: the last view's loss weighs W times the first's, "
                   "linear in between (mean 1), so that the gradient favours what the memory adds "
                   "as views accumulate; 1 = every view alike")


def build_parser(description: str | None = None) -> argparse.ArgumentParser:
    """The training command's parser; the groups' order is the order of ``--help``."""
    p = argparse.ArgumentParser(
        prog="python -m completion.train",
        description=description,
        formatter_class=DefaultsAndRawDescription,
    )
    _add_data_options(p)
    _add_schedule_options(p)
    _add_run_options(p)
    _add_view_options(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def check_args(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """What argparse's types cannot say alone (ranges, options that need a multi-view model, a
    ``--config`` the model accepts); exits through ``p.error`` at the first problem."""
    for name in ("views", "steps", "val_every", "batch_size", "threads"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be ≥ 1, got {getattr(args, name)}")
    for flag in ("blank_local", "hide_views", "hide_context"):  # view-masking probabilities
        value, name = getattr(args, flag), "--" + flag.replace("_", "-")
        if not 0.0 <= value < 1.0:
            p.error(f"{name} must be in [0, 1), got {value}")
        if value and args.model == "single_view":
            p.error(f"{name} needs a multi-view model (single_view has no context tower)")
    if not (1.0 <= args.late_weight <= 10.0):
        p.error(f"--late-weight must be in [1, 10], got {args.late_weight}")
    if args.late_weight != 1 and args.model == "single_view":
        p.error("--late-weight needs a multi-view model (single_view has no memory)")
    if not (args.jaccard_weight >= 0 and math.isfinite(args.jaccard_weight)):
        p.error(f"--jaccard-weight must be a finite number ≥ 0, got {args.jaccard_weight}")
    if not 0.0 <= args.ema < 1.0:
        p.error(f"--ema must be in [0, 1), got {args.ema}")
    try:
        default_config(args.model, **args.config)
    except (TypeError, ValueError) as err:
        p.error(f"--config: {err}")


def parse_args(argv: list[str], description: str | None = None) -> argparse.Namespace:
    """The training command's options, checked, with the command line that gave them
    (``args.command``, stored in the checkpoint)."""
    p = build_parser(description)
    args = p.parse_args(argv)
    check_args(p, args)
    args.command = "python -m completion.train " + shlex.join(argv)
    return args
