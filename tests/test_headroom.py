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


def test_headroom_cli_prints_the_table_and_rejects_a_missing_model(capsys, tmp_path):
    with pytest.raises(SystemExit):
        main(["--models", str(tmp_path / "missing.pt")])
    assert "does not exist" in capsys.readouterr().err
    assert main(["--models", "single_view", "--count", "1"]) == 0
    out = capsys.readouterr().out
    assert "single_view" in out and "sliding object's share" in out
