"""completion.widen: a wider U-Net that computes the same logits and can learn with its new
channels; the command line writes a checkpoint that a run with those channels loads whole."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from test_model import random_views, tiny_config

from completion.model import ModelConfig, build_model, read_checkpoint, save_checkpoint
from completion.train import warm_start
from completion.widen import main, widen

SHIFT = tiny_config("mvp", context="both", place_window=1, shift_heads=1, shift_channels=2)
CASES = [(tiny_config(kind), channels) for kind in ("single_view", "mvp", "lstm")
         for channels in ((2, 4, 16), (3, 6, 8))] + [(SHIFT, (2, 6, 16))]


def _scrambled(config: ModelConfig) -> torch.nn.Module:
    """A model whose every weight is random (no zero-initialised layer hides a mistake)."""
    model = build_model(config).eval()
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.2 * torch.randn(p.shape, generator=g))
    return model


@pytest.mark.parametrize(("config", "channels"), CASES,
                         ids=[f"{c.kind}-{c.shift_heads}-{w}" for c, w in CASES])
def test_a_widened_model_gives_the_same_logits_and_its_new_channels_learn(
    config: ModelConfig, channels: tuple[int, ...]
) -> None:
    model = _scrambled(config)
    wide = widen(model, channels).eval()
    assert wide.config.channels == channels and wide.n_params() > model.n_params()
    x = random_views(2, 3)
    with torch.no_grad():
        torch.testing.assert_close(wide(x), model(x), atol=1e-5, rtol=1e-5)
    wide.train()
    wide(x).square().mean().backward()
    # the bottleneck conv's weights that read the new channels start at zero and get gradients
    level = len(channels) - 1
    conv = wide.encoder.levels[level][2]
    old = config.channels[level]
    assert old == channels[level] or float(conv.weight.detach()[:old, old:].abs().max()) == 0.0
    assert conv.weight.grad is not None and float(conv.weight.grad.abs().sum()) > 0


def test_narrower_channels_are_refused() -> None:
    with pytest.raises(ValueError, match="at least"):
        widen(build_model(tiny_config("mvp")), (2, 4, 4))
    with pytest.raises(ValueError, match="3 levels"):
        widen(build_model(tiny_config("mvp")), (2, 4))
    with pytest.raises(ValueError, match="finest level"):
        widen(build_model(SHIFT), (3, 4, 8))


def test_the_command_writes_a_checkpoint_a_wider_run_loads_whole(tmp_path: Path, capsys) -> None:
    src, out = tmp_path / "mvp.pt", tmp_path / "wide.pt"
    save_checkpoint(_scrambled(tiny_config("mvp")), src, threshold=0.6, name="mvp", step=7)
    main([str(src), str(out), "--channels", "2:4:16", "--kind", "single_view"])
    assert "parameters" in capsys.readouterr().out
    payload = read_checkpoint(out)
    assert payload["config"]["kind"] == "single_view" and payload["threshold"] == 0.6
    run = build_model(ModelConfig.from_dict(payload["config"]))
    assert warm_start(run, out) == []  # the same config: loaded whole
    with pytest.raises(SystemExit):
        main([str(src), str(out), "--channels", "2:x"])
    with pytest.raises(SystemExit):
        main([str(tmp_path / "missing.pt"), str(out), "--channels", "2:4:16"])
