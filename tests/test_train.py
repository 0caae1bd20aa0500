import json

import pytest

from completion import data
from completion.model import load_model, read_checkpoint
from completion.train import main

TINY = "channels=2:4:8,embed_dim=16,n_heads=2,n_features=8"


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    root = tmp_path_factory.mktemp("shards")
    for split in ("train", "val"):
        data.generate(["camera_pan", "object_hiding"], split, 2, seed=0, out=root / split,
                      views=3, progress=False)
    return root


def test_train_writes_best_checkpoint_and_resumes(shards, tmp_path, capsys):
    out = tmp_path / "w" / "tiny.pt"
    args = ["--model", "mvp", "--views", "2", "--train-dir", str(shards / "train"),
            "--val-dir", str(shards / "val"), "--train-count", "0", "--val-count", "0",
            "--epochs", "2", "--minutes", "0", "--batch-size", "2", "--config", TINY,
            "--out", str(out), "--run-dir", str(tmp_path / "run"), "--quiet"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["epochs"] == 2 and summary["steps"] == 4
    payload = read_checkpoint(out)
    assert payload["views"] == 2 and payload["command"].startswith("python -m completion.train")
    assert set(payload["val"]["0.50"]["per_condition"]) == {"camera_pan", "object_hiding"}
    import torch

    assert {v.dtype for v in payload["state_dict"].values() if v.is_floating_point()} == {
        torch.float16  # shipped weights are stored in half precision, loaded as fp32
    }
    model = load_model(out)
    assert model.config.embed_dim == 16 and model.threshold == 0.5
    # Resume continues from the saved step count rather than starting over.
    assert main([*args[:-1], "--resume", "--epochs", "3", "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["steps"] == 6


def test_select_threshold_writes_one_threshold_into_every_checkpoint(shards, tmp_path, capsys):
    outs = []
    for kind in ("single_view", "lstm"):
        out = tmp_path / f"{kind}.pt"
        main(["--model", kind, "--views", "3", "--train-dir", str(shards / "train"),
              "--val-dir", str(shards / "val"), "--train-count", "0", "--val-count", "0",
              "--epochs", "1", "--minutes", "0", "--config", TINY, "--out", str(out),
              "--run-dir", str(tmp_path / kind), "--quiet"])
        outs.append(out)
    capsys.readouterr()
    assert main(["select-threshold", *map(str, outs)]) == 0
    chosen = json.loads(capsys.readouterr().out)["threshold"]
    assert {load_model(o).threshold for o in outs} == {chosen}
    assert main(["select-threshold", str(tmp_path / "missing.pt")]) == 2


def test_bad_arguments_are_explained(capsys):
    with pytest.raises(SystemExit):
        main(["--model", "mvp", "--conditions", "pan", "--out", "x.pt"])
    assert "expected 'all' or a comma list" in capsys.readouterr().err
