import numpy as np
import pytest
import torch

from completion.headroom import headroom, main


class _Constant(torch.nn.Module):
    """Predicts every voxel empty (or full): logits of one sign."""

    def __init__(self, sign: float) -> None:
        super().__init__()
        self.sign = sign

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.full_like(x, 10.0 * self.sign)


def test_headroom_is_what_the_sliding_object_adds():
    out = headroom({"empty": _Constant(-1), "full": _Constant(1)}, split="test", count=2, views=3)
    empty, full, share = out["per_view"]["empty"], out["per_view"]["full"], out["sliding_share"]
    assert empty["alone"] == [0.0] * 3
    # predicting nothing but the sliding object's truth scores its share of the target
    assert np.allclose(empty["with_sliding_truth"], share, atol=1e-4)
    assert all(0.0 < s < 1.0 for s in share)
    # the truth added to a prediction never lowers its Jaccard; a full grid gains nothing
    assert full["with_sliding_truth"] == full["alone"]
    assert empty["sliding_recall"] == [0.0] * 3 and full["sliding_recall"] == [1.0] * 3
    # what is drawn around the slider: nothing (no offset to give), or everything (the slider's
    # share of its neighbourhood, centred on it)
    assert empty["sliding_precision"] == [0.0] * 3
    assert all(np.isnan(x) for x in empty["sliding_offset_x"])
    assert all(0.0 < x < 1.0 for x in full["sliding_precision"])
    assert all(0.0 <= x < 1.0 for x in full["sliding_offset_x"])


class _Surface(torch.nn.Module):
    """Predicts exactly the observed surface (the input): no completion, no memory."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 20.0 * x - 10.0


def test_own_slider_moved_carries_the_first_views_completion_to_where_the_slider_is():
    from completion.headroom import moved, slider_shift
    from completion.scenes import make_sequence

    seq = make_sequence("slide_behind", "test", 0, 0, views=6)
    shifts = [slider_shift(seq, v) for v in range(6)]
    assert shifts[0].tolist() == [0, 0, 0]
    assert any(s[0] != 0 for s in shifts[1:]) and all(s[1] == 0 for s in shifts)  # along x only
    box = np.zeros((40, 40, 40), dtype=bool)
    box[1:3, 5:7, 9] = True
    assert np.array_equal(moved(box, np.array([3, 0, -1])), np.roll(box, (3, -1), axis=(0, 2)))
    assert moved(box, np.array([-5, 0, 0])).sum() == 0  # off the grid

    out = headroom({"surface": _Surface(), "empty": _Constant(-1)}, split="test", count=2, views=6)
    surface, empty = out["per_view"]["surface"], out["per_view"]["empty"]
    assert surface["own_slider_moved"][0] == pytest.approx(surface["alone"][0])  # nothing moved yet
    # the slider's seen surface carried along lands on the slider: the score only rises
    assert all(o >= a for o, a in zip(surface["own_slider_moved"], surface["alone"], strict=True))
    assert np.mean(surface["own_slider_moved"]) > np.mean(surface["alone"])
    assert empty["own_slider_moved"] == empty["alone"] == [0.0] * 6  # nothing to carry
    # the seen surface is the slider's more often than the whole neighbourhood is
    full = headroom({"full": _Constant(1)}, split="test", count=2, views=6)["per_view"]["full"]
    assert all(s > f for s, f in zip(surface["sliding_precision"], full["sliding_precision"],
                                     strict=True))


def test_surfaces_moved_adds_the_sliders_seen_voxels_where_the_slider_is():
    from completion.headroom import observed_surfaces_moved

    inputs = np.zeros((3, 40, 40, 40), dtype=bool)
    sliding = np.zeros_like(inputs)
    for v, i in enumerate((10, 14, 18)):  # the slider moves 4 voxels along x per view
        sliding[v, i:i + 3, 5:8, 5:8] = True
        inputs[v, i:i + 3, 5:8, 5] = True  # its front face is seen
        inputs[v, i + 1, 6, 7] = v == 1  # one voxel of its back only in view 1
    inputs[:, 30, 30, 30] = True  # the front object's voxel, never carried
    shifts = [np.array([4 * v, 0, 0]) for v in range(3)]
    first = observed_surfaces_moved(inputs, sliding, shifts, every_view=False)
    every = observed_surfaces_moved(inputs, sliding, shifts, every_view=True)
    assert np.array_equal(first[0], inputs[0]) and np.array_equal(every[0], inputs[0])
    # view 0's face lands on each later view's face: nothing new, nothing off the slider
    assert np.array_equal(first, inputs)
    # only "every view" carries view 1's back voxel on into view 2
    assert not first[2, 19, 6, 7] and every[2, 19, 6, 7] and every[1, 15, 6, 7]
    assert every.sum() == first.sum() + 1 and (every[:, 30, 30, 30]).all()

    out = headroom({"surface": _Surface()}, split="test", count=2, views=6)["per_view"]["surface"]
    # a model that draws its input: the carried surface lands on the slider, so it only gains
    assert out["first_surface_moved"][0] == pytest.approx(out["alone"][0])
    assert all(f >= a - 1e-9 for f, a in zip(out["first_surface_moved"], out["alone"],
                                             strict=True))
    assert np.mean(out["all_surfaces_moved"]) >= np.mean(out["first_surface_moved"]) - 1e-9
    # a model that draws only what it sees completes part of the slider; one that draws nothing
    # completes none of it
    both = headroom({"surface": _Surface(), "empty": _Constant(-1)}, split="test", count=2, views=3)
    assert 0.0 < both["per_view"]["surface"]["first_view_slider"][0] < 1.0
    assert both["per_view"]["empty"]["first_view_slider"] == [0.0]
    assert len(both["slider_size"]) == 4 and all(n > 0 for n in both["slider_size"])


def test_completions_averaged_carries_the_mean_of_the_views_that_show_the_slider():
    from completion.headroom import completions_averaged

    inputs = np.zeros((3, 40, 40, 40), dtype=bool)
    sliding = np.zeros_like(inputs)
    probability = np.zeros(inputs.shape, dtype=np.float32)
    for v, i in enumerate((10, 14, 18)):
        sliding[v, i : i + 3, 5:8, 5:8] = True
        inputs[v, i : i + 3, 5:8, 5] = v < 2  # seen in views 0 and 1, hidden in view 2
    probability[0, 10:13, 5:8, 5:8] = 0.9  # view 0 completes the whole slider
    probability[1, 14:17, 5:8, 5:7] = 0.9  # view 1 misses its back layer
    probability[1, 30, 30, 30] = 0.9  # and draws a voxel far from it: never carried
    shifts = [np.array([4 * v, 0, 0]) for v in range(3)]
    out = completions_averaged(probability, sliding, inputs, shifts, 0.6)
    assert np.array_equal(out[0], probability[0] >= 0.6)
    # the mean of 0.9 and 0.9 keeps the front layers, the mean of 0.9 and 0 loses the back one
    assert out[1, 14:17, 5:8, 5:7].all() and not out[1, 14:17, 5:8, 7].any()
    assert out[2, 18:21, 5:8, 5:7].all() and out.sum() == 27 + 18 + 1 + 18
    assert not out[2, 30, 30, 30]
    assert np.array_equal(completions_averaged(probability, sliding, inputs, shifts, 0.4)[2],
                          sliding[2])  # the mean 0.45 passes a lower threshold


def test_headroom_cli_prints_the_table_and_rejects_a_missing_model(capsys, tmp_path):
    with pytest.raises(SystemExit):
        main(["--models", str(tmp_path / "missing.pt")])
    assert "does not exist" in capsys.readouterr().err
    assert main(["--models", "single_view", "--count", "1"]) == 0
    out = capsys.readouterr().out
    assert "single_view" in out and "sliding object's share" in out and "own slider moved" in out
    assert "slider precision" in out and "slider |dx|" in out
    assert "first surface moved" in out and "all surfaces moved" in out
    assert "slider completed in view 0" in out and "voxels across" in out
    assert "completions averaged" in out
    assert main(["--models", "single_view", "--count", "1", "--threshold", "0.99"]) == 0
    assert capsys.readouterr().out != out  # a stricter threshold draws fewer voxels
    for bad in ("1", "0", "half"):
        with pytest.raises(SystemExit):
            main(["--models", "single_view", "--threshold", bad])
        assert "expected a number in (0, 1)" in capsys.readouterr().err


def test_shift_quantum_rounds_the_slider_translation_and_rejects_zero(capsys):
    from completion.headroom import quantised

    assert quantised(np.array([-23, 0, 5]), 1).tolist() == [-23, 0, 5]
    assert quantised(np.array([-23, 0, 5]), 8).tolist() == [-24, 0, 8]
    assert quantised(np.array([22, 0, -1]), 4).tolist() == [24, 0, 0]
    surface = {"surface": _Surface()}
    exact = headroom(surface, split="test", count=1, views=6)
    assert exact["shift_quantum"] == 1
    # a quantum wider than the grid leaves the first view's completion where it was seen
    still = headroom(surface, split="test", count=1, views=6, shift_quantum=1000)
    s, e = still["per_view"]["surface"], exact["per_view"]["surface"]
    assert s["alone"] == e["alone"] and s["own_slider_moved"][0] == e["own_slider_moved"][0]
    assert s["own_slider_moved"] != e["own_slider_moved"]
    with pytest.raises(SystemExit):
        main(["--models", "single_view", "--shift-quantum", "0"])
    assert "--shift-quantum" in capsys.readouterr().err


def test_shift_move_error_measures_the_memorys_move_against_the_sliders(capsys, tmp_path):
    from test_model import tiny_config

    from completion.headroom import shift_move_error
    from completion.model import build_model, save_checkpoint

    model = build_model(tiny_config("mvp", shift_heads=2, shift_channels=2)).eval()
    x = torch.zeros(1, 4, 40, 40, 40)
    move = np.array([0.0, -3.0, -8.5, -8.5])
    write = torch.tensor([[4.0, 6.0]]).repeat(4, 1)  # cells, per view and head
    read = write + torch.tensor([[0.0, 0.0], [-1.5, 0.0], [-4.25, -1.0], [-4.0, -1.0]])
    model.shift_memory.references = lambda level, frames: (write, read)
    error = shift_move_error(model, x, move)  # (H, L), voxels: 2 a cell
    assert np.allclose(error[0], [0.0, 0.0, 0.0, 0.5]) and np.allclose(error[1], [0, 3, 6.5, 6.5])
    assert shift_move_error(_Surface(), x, move).shape == (0, 4)  # no shift memory, no figure

    fresh = build_model(tiny_config("mvp", shift_heads=2, shift_channels=2)).eval()
    out = headroom({"fresh": fresh, "surface": _Surface()}, split="test", count=2, views=6)
    assert np.array(out["per_view"]["fresh"]["shift_move_error"]).shape == (2, 6)
    assert max(out["slider_move_x"]) > 4 and out["slider_move_x"][0] == 0
    assert out["per_view"]["surface"]["shift_move_error"] == []
    exact = out["per_view"]["fresh"]["shift_exact"]  # its read starts at zero: placing it is moot
    assert exact == out["per_view"]["fresh"]["alone"]
    assert out["per_view"]["surface"]["shift_exact"] == []
    save_checkpoint(fresh, tmp_path / "fresh.pt")
    assert main(["--models", str(tmp_path / "fresh.pt"), "--count", "1"]) == 0
    printed = capsys.readouterr().out
    assert "shift memory head" in printed and "standing exactly at the slider" in printed


def test_standing_at_moves_what_was_written_by_the_given_cells_and_then_lets_go():
    from test_model import tiny_config

    from completion.headroom import standing_at
    from completion.model import build_model

    model = build_model(tiny_config("mvp", shift_heads=2, shift_channels=2)).eval()
    torch.nn.init.normal_(model.shift_memory.out.weight)  # so that the read reaches the output
    x = (torch.rand(1, 4, 40, 40, 40, generator=torch.Generator().manual_seed(0)) > 0.9).float()
    with torch.no_grad():
        learned = model(x)
        with standing_at(model, torch.tensor([3.0, 4.0, 5.5, 5.5])):
            moving = model(x)
        with standing_at(model, torch.tensor([10.0, 11.0, 12.5, 12.5])):
            same_moves = model(x)  # the same moves between frames from another origin
        with standing_at(model, torch.tensor([3.0, 3.0, 3.0, 3.0])):
            still = model(x)
        after = model(x)
    origin = (moving - same_moves).abs().max()  # only the moves between frames count
    first = (moving[:, 0] - still[:, 0]).abs().max()  # the first view reads only itself
    moves = (moving[:, 1:] - still[:, 1:]).abs().max()
    assert moves > 100 * max(origin, first), (moves, origin, first)
    assert torch.equal(after, learned) and "_frames" not in vars(model.shift_memory)
