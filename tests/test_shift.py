"""The shift memory (completion.shift): a shape written in one view's frame is read in another's
moved by the difference of the two reference positions, fractions of a cell included; the
memory's size does not grow; a checkpoint without it warm-starts it exactly."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from test_model import ATOL, random_views, scrambled, tiny_config

from completion.model import ModelConfig, build_model, save_checkpoint, state_nbytes
from completion.shift import fourier_read, fourier_write, frame_at, frame_of
from completion.train import param_groups, warm_start

N = 20  # cells along i at the finest level of a 40³ grid


def _moved(i0: int, p_write: float, p_read: float) -> torch.Tensor:
    """A unit written at cell i0 of one row, read back: the profile along i (N,)."""
    content = torch.zeros(1, 1, 1, N, 1, 1)
    content[0, 0, 0, i0] = 1.0
    k = torch.arange(N, dtype=torch.float32)
    omega = math.pi * k / N
    gain = (torch.where(k == 0, 1.0, 2.0) / (2 * N) * 0.5 * (1 + torch.cos(math.pi * k / N)))
    re, im = fourier_write(content, frame_at(torch.tensor([[p_write]]), omega), omega)
    return fourier_read(re, im, frame_at(torch.tensor([[p_read]]), omega), gain[None], omega,
                        N)[0, 0, 0, :, 0, 0]


@pytest.mark.parametrize("shift", [3.0, 3.5, -2.25, 0.0])
def test_a_unit_comes_back_moved_by_the_difference_of_the_references(shift: float) -> None:
    i0 = 8
    profile = _moved(i0, p_write=4.0, p_read=4.0 + shift)
    cells = torch.arange(N, dtype=torch.float32)
    near = (cells - (i0 + shift)).abs() <= 4  # the peak and its flanks, no border in reach
    centre = (profile[near] * cells[near]).sum() / profile[near].sum()
    assert abs(float(centre) - (i0 + shift)) < 0.05, (shift, profile)
    assert int(profile.argmax()) in {math.floor(i0 + shift), math.ceil(i0 + shift)}
    assert float(profile.sum()) == pytest.approx(1.0, abs=0.02)  # the unit's mass survives
    assert float(profile[~near].abs().max()) < 0.02  # little ringing far from it


@torch.no_grad()
def test_a_view_stands_among_the_cells_it_sees_and_uniformly_at_first() -> None:
    model = build_model(tiny_config("mvp", shift_heads=1, shift_channels=2))
    frames = torch.zeros(2, 40, 40, 40)
    frames[0, 10:12, 20, 20] = 1  # cell i = 5
    frames[0, 30, 8, 3] = 1  # cell i = 15
    levels = torch.randn(2, 2, N, N, N)
    p_write, p_read = model.shift_memory.references(levels, frames)
    assert p_write[:, 0].tolist() == pytest.approx([10.0, 9.5])  # between the two; empty: anywhere
    assert p_read[:, 0].tolist() == pytest.approx([10.0, 9.5])


def test_only_the_difference_of_the_references_matters() -> None:
    torch.testing.assert_close(_moved(6, 2.0, 5.5), _moved(6, 9.0, 12.5), atol=1e-5, rtol=0)


def test_a_frame_of_one_cell_is_that_cell_and_a_spread_frame_blends_the_moves() -> None:
    k = torch.arange(N, dtype=torch.float32)
    omega = math.pi * k / N
    one = torch.zeros(1, 1, N)
    one[0, 0, 7] = 1.0
    for a, b in zip(frame_of(one, omega), frame_at(torch.tensor([[7.0]]), omega), strict=True):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=0)
    # standing at 2 or 12 with even odds: a unit written from 2 arrives half moved by 0 cells,
    # half by 10
    two = torch.zeros(1, 1, N)
    two[0, 0, 2] = two[0, 0, 12] = 0.5
    gain = torch.where(k == 0, 1.0, 2.0) / (2 * N) * 0.5 * (1 + torch.cos(math.pi * k / N))
    content = torch.zeros(1, 1, 1, N, 1, 1)
    content[0, 0, 0, 4] = 1.0
    re, im = fourier_write(content, frame_at(torch.tensor([[2.0]]), omega), omega)
    profile = fourier_read(re, im, frame_of(two, omega), gain[None], omega, N)[0, 0, 0, :, 0, 0]
    assert float(profile[4]) == pytest.approx(float(profile[14]), abs=1e-5)
    assert float(profile[4]) > 0.1
    assert float(profile[8:11].abs().max()) < 0.02


@torch.no_grad()
def test_read_streams_as_in_parallel_and_the_state_keeps_its_size() -> None:
    model = scrambled(tiny_config("mvp", shift_heads=2, shift_channels=3, shift_freqs=12))
    memory = model.shift_memory
    levels = torch.randn(2 * 5, 2, N, N, N)  # (B·L, C0, n, n, n), C0 of the tiny config
    frames = random_views(2, 5).flatten(0, 1)
    frames[3] = 0  # an empty view stands anywhere
    parallel = memory(levels, frames, (2, 5))
    assert parallel.abs().max() > 0.1
    state, sizes, outs = memory.init_state(2, device=torch.device("cpu")), set(), []
    for t in range(5):
        out, state = memory.step(levels.view(2, 5, *levels.shape[1:])[:, t],
                                 frames.view(2, 5, *frames.shape[1:])[:, t], state)
        outs.append(out)
        sizes.add(state_nbytes(state))
    torch.testing.assert_close(torch.stack(outs, 1).flatten(0, 1), parallel, atol=ATOL, rtol=0)
    assert sizes == {4 * (2 * 2 * 2 * 3 * 12 * N * N + 2 * 2 * N * N)}  # re, im, mass; float32


@torch.no_grad()
def test_warm_start_without_it_is_exact_and_then_it_carries_earlier_views(
    tmp_path: Path,
) -> None:
    base = tiny_config("mvp", context="both", place_window=1, value_rotation=30)
    save_checkpoint(scrambled(base), tmp_path / "mvp.pt")
    source = build_model(base).eval()
    warm_start(source, tmp_path / "mvp.pt")
    model = build_model(base.replace(shift_heads=2, shift_channels=2)).eval()
    fresh = warm_start(model, tmp_path / "mvp.pt")
    assert fresh and all(name.startswith("shift_memory.") for name in fresh), fresh
    seq = random_views(1, 4)
    torch.testing.assert_close(model(seq), source(seq), atol=ATOL, rtol=0)
    changed = seq.clone()
    changed[0, 0] = random_views(1, 1, seed=3, density=0.3)[0, 0]  # only view 0 differs
    for bridge in (model.bridge, model.place_bridge):  # the coarse paths carry nothing
        torch.nn.init.zeros_(bridge.expand.weight)
        torch.nn.init.zeros_(bridge.expand.bias)
    assert torch.equal(model(changed)[0, 3], model(seq)[0, 3])
    torch.nn.init.normal_(model.shift_memory.out.weight, std=0.5)
    assert (model(changed)[0, 3] - model(seq)[0, 3]).abs().max() > 1e-4


@torch.no_grad()
def test_writing_the_decoded_view_warm_starts_exactly_and_then_changes_what_is_read(
    tmp_path: Path,
) -> None:
    base = tiny_config("mvp", shift_heads=2, shift_channels=2)
    save_checkpoint(scrambled(base), tmp_path / "mvp.pt")
    source = build_model(base).eval()
    warm_start(source, tmp_path / "mvp.pt")
    model = build_model(base.replace(shift_decoded=True)).eval()
    assert warm_start(model, tmp_path / "mvp.pt") == ["shift_memory.value_decoded.weight"]
    seq = random_views(1, 4)
    torch.testing.assert_close(model(seq), source(seq), atol=ATOL, rtol=0)
    torch.nn.init.normal_(model.shift_memory.value_decoded.weight, std=0.5)
    assert (model(seq) - source(seq)).abs().max() > 1e-4
    # advance (no decoding) leaves the state that step leaves
    state = model.init_state(1)
    _, stepped = model.step(state, seq[:, 0])
    advanced = model.advance(state, seq[:, 0])
    assert stepped.keys() == advanced.keys()
    for name in stepped:
        torch.testing.assert_close(advanced[name], stepped[name], atol=ATOL, rtol=0)


def test_place_lr_takes_the_shift_memory_and_bad_configs_raise() -> None:
    model = build_model(tiny_config("mvp", context="both", shift_heads=1))
    groups = param_groups(model, 1e-4, 1e-3)
    fast = {id(p) for p in groups[1]["params"]}
    assert all(id(p) in fast for p in model.shift_memory.parameters())
    for overrides, message in (
        ({"kind": "single_view", "shift_heads": 1}, "needs a multi-view model"),
        ({"channels": (4,), "shift_heads": 1}, "two U-Net levels"),
        ({"shift_heads": -1}, "shift_heads must be >= 0"),
        ({"shift_heads": 1, "shift_freqs": 21}, "shift_freqs in"),
        ({"shift_heads": 1, "shift_channels": 0}, "shift_channels >= 1"),
        ({"shift_decoded": True}, "shift_decoded needs the shift memory"),
    ):
        with pytest.raises(ValueError, match=message):
            ModelConfig(**{**tiny_config().to_dict(), **overrides})
