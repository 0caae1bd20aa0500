"""Widen a checkpoint's U-Net without changing what it computes, to train more capacity from it.

    python -m completion.widen CKPT OUT --channels 16:32:128 [--kind single_view] [--seed N]

Every tensor whose shape grows keeps its old values at the old channels' places; the new output
channels keep their fresh init, and old outputs read the new input channels with zero weights,
so the widened model gives the old one's logits and its new channels learn from there (their
activations are not zero, so the zero weights that read them get gradients). A grown axis
(c → C) maps old index i to i, except the input of the decoder's convs after a concatenation
(up-sampled ++ skip, 2c → 2C), where the skip's half moves to C + i. The result is checked:
``OUT`` is written only if the two models' logits agree on a random sequence.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import torch
from torch import Tensor

from completion.model import (
    CompletionModel,
    ModelConfig,
    build_model,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
)
from completion.train import warm_start


def _index_map(name: str, axis: int, old: int, new: int) -> Tensor:
    """Where old index i of ``name``'s ``axis`` lands in the widened tensor."""
    if name.startswith("decoder.fuse.") and name.endswith(".0.weight") and axis == 1:
        half, new_half = old // 2, new // 2  # (up-sampled ++ skip): the skip's half moves
        return torch.cat((torch.arange(half), new_half + torch.arange(half)))
    return torch.arange(old)


def widen(model: CompletionModel, channels: Sequence[int], *, seed: int = 0) -> CompletionModel:
    """A copy of ``model`` with U-Net ``channels`` (each level at least as wide) that computes
    the same logits."""
    old_channels, channels = model.config.channels, tuple(int(c) for c in channels)
    if len(channels) != len(old_channels) or any(
            c < o for c, o in zip(channels, old_channels, strict=True)):
        raise ValueError(f"channels must have {len(old_channels)} levels, each at least "
                         f"{old_channels}, got {channels}")
    config = model.config
    if config.shift_heads and channels[0] > old_channels[0]:
        raise ValueError("cannot widen the finest level of a model with a shift memory (it "
                         "reads that level's channels joined with the cells' coordinates); "
                         "widen the other levels")
    wide = build_model(config.replace(channels=channels, seed=seed))
    state = wide.state_dict()
    transposed = {f"{name}.weight" for name, m in model.named_modules()
                  if isinstance(m, torch.nn.ConvTranspose3d)}  # weights (in, out, …)
    for name, old in model.state_dict().items():
        new = state[name].clone()
        if new.shape == old.shape:
            new = old.clone()
        else:
            maps = [_index_map(name, axis, a, b)
                    for axis, (a, b) in enumerate(zip(old.shape, new.shape, strict=True))]
            if old.dim() > 1:  # old outputs read the new inputs with zero weights
                out_dim, in_dim = (1, 0) if name in transposed else (0, 1)
                rows = new.index_select(out_dim, maps[out_dim])
                fresh_in = torch.ones(new.shape[in_dim], dtype=torch.bool)
                fresh_in[maps[in_dim]] = False
                index: list[slice | Tensor] = [slice(None)] * new.dim()
                index[in_dim] = fresh_in
                rows[tuple(index)] = 0
                new.index_copy_(out_dim, maps[out_dim], rows)
            new[torch.meshgrid(*maps, indexing="ij")] = old
        state[name] = new
    wide.load_state_dict(state)
    return wide


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m completion.widen", description=__doc__.split(
        "\n\n")[0])
    p.add_argument("checkpoint", type=Path, help="a checkpoint of any model")
    p.add_argument("out", type=Path, help="where to write the widened checkpoint")
    p.add_argument("--channels", required=True,
                   help="the U-Net's new channels per level, e.g. 16:32:128")
    p.add_argument("--seed", type=int, default=0, help="seed of the new channels' fresh init")
    p.add_argument("--kind", choices=("single_view",), default=None,
                   help="keep only the local tower and decoder (a Single-View from any model)")
    args = p.parse_args(argv)
    try:
        channels = tuple(int(c) for c in args.channels.split(":"))
    except ValueError:
        p.error(f"--channels: expected integers separated by ':', got {args.channels!r}")
    if not args.checkpoint.is_file():
        p.error(f"no such checkpoint {args.checkpoint}")
    payload = read_checkpoint(args.checkpoint)
    if args.kind:  # the local tower and decoder, as --init-from gives them to Single-View
        saved = ModelConfig.from_dict(payload["config"])
        model = build_model(ModelConfig(kind="single_view", grid_size=saved.grid_size,
                                        channels=saved.channels, conv_kernel=saved.conv_kernel,
                                        norm=saved.norm, top_channels=saved.top_channels))
        warm_start(model, args.checkpoint)
    else:
        model = load_checkpoint(args.checkpoint)
    config = model.config
    try:
        wide = widen(model.eval(), channels, seed=args.seed)
    except ValueError as err:
        p.error(str(err))
    g = config.grid_size
    x = (torch.rand(2, 4, g, g, g, generator=torch.Generator().manual_seed(0)) < 0.05).float()
    with torch.no_grad():
        gap = (model(x) - wide.eval()(x)).abs().max().item()
    if gap > 1e-4:
        raise SystemExit(f"widened model's logits differ by {gap:.2e}; nothing written")
    save_checkpoint(wide, args.out, threshold=payload.get("threshold", 0.5),
                    name=payload.get("name", config.kind), step=payload.get("step", 0))
    print(f"wrote {args.out}: channels {config.channels} -> {channels}, parameters "
          f"{model.n_params():,} -> {wide.n_params():,}, largest logit difference {gap:.1e}")


if __name__ == "__main__":
    main()
