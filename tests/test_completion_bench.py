"""completion.bench: JSON of the documented shape; MVP memory flat in L, MVT cache growing."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from completion.bench import bench_model, main
from completion.config import ModelConfig
from completion.model import build_model

torch.set_num_threads(1)

ROOT = Path(__file__).resolve().parents[1]


def tiny(kind: str) -> ModelConfig:
    return ModelConfig(kind=kind, channels=(2, 4, 8), embed_dim=16, n_heads=2, n_features=8)


def test_bench_model_reports_flat_mvp_state_and_growing_mvt_cache() -> None:
    views = [1, 5, 40]
    mvp = bench_model(build_model(tiny("mvp")), views=views, repeats=2)
    mvt = bench_model(build_model(tiny("mvt")), views=views, repeats=2)
    for entry in (mvp, mvt):
        assert list(entry["latency_ms"]) == list(entry["cpu_ms"]) == ["1", "5", "40"]
        assert all(v > 0 for v in entry["latency_ms"].values())
        assert entry["params"] > 0
    assert len(set(mvp["state_bytes"].values())) == 1
    assert len(set(mvp["state_tensor_bytes"].values())) == 1
    grow = [mvt["state_tensor_bytes"][str(v)] for v in views]
    assert grow[0] < grow[1] < grow[2]
    per_view = (grow[2] - grow[1]) / 35  # one key and one value vector (D floats each) per view
    assert per_view == 2 * 16 * 4


def test_cli_prints_json_of_the_documented_shape(capsys: pytest.CaptureFixture[str]) -> None:
    main(["--models", "mvp,mvt", "--views", "1,3", "--repeats", "1", "--threads", "1"])
    report = json.loads(capsys.readouterr().out)
    assert set(report["models"]) == {"mvp", "mvt"}
    for entry in report["models"].values():
        assert set(entry["latency_ms"]) == {"1", "3"}
        assert set(entry["state_bytes"]) == {"1", "3"}
        assert all(isinstance(v, float) for v in entry["latency_ms"].values())
        assert all(isinstance(v, int) for v in entry["state_bytes"].values())
        assert isinstance(entry["params"], int) and entry["params"] > 0
        assert entry["weights"] in ("shipped", "fresh")
    assert report["device"] == "cpu" and report["threads"] == 1 and report["batch"] == 1
    assert (
        report["models"]["mvp"]["state_bytes"]["1"] == report["models"]["mvp"]["state_bytes"]["3"]
    )


@pytest.mark.parametrize(
    "argv",
    [["--models", "gpt"], ["--views", "1,x"], ["--views", "-1"], ["--repeats", "0"]],
)
def test_cli_rejects_bad_arguments(argv: list[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2


def test_module_entry_point_runs() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "completion.bench", "--models", "single_view", "--views", "1"]
        + ["--repeats", "1"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    report = json.loads(result.stdout)
    assert set(report["models"]["single_view"]["latency_ms"]) == {"1"}
