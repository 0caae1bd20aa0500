import subprocess
import sys

import numpy as np
import pytest

from completion import data


def test_generate_save_load_round_trip(tmp_path):
    paths = data.generate(
        ["camera_pan", "object_reveal"],
        "val",
        1,
        seed=3,
        out=tmp_path,
        workers=1,
        views=3,
        keep_depth=True,
        progress=False,
    )
    assert [p.name for p in paths] == [
        "camera_pan_val_s3_00000.npz",
        "object_reveal_val_s3_00000.npz",
    ]
    seq = data.load_sequence(paths[0])
    assert seq.inputs.shape == (3, 40, 40, 40) and seq.inputs.dtype == bool
    assert seq.depth.shape == (3, 240, 320) and seq.mask.shape == (3, 240, 320)
    assert seq.meta["seed"] == 3 and seq.meta["intrinsics"]["width"] == 320
    from completion.scenes import make_sequence

    again = make_sequence("camera_pan", "val", 0, 3, views=3)
    assert np.array_equal(again.targets, seq.targets)


def test_load_rejects_non_shards(tmp_path):
    bad = tmp_path / "x.npz"
    np.savez(bad, a=np.zeros(3))
    with pytest.raises(ValueError, match="missing"):
        data.load_sequence(bad)
    (tmp_path / "y.npz").write_bytes(b"junk")
    with pytest.raises(ValueError, match="cannot read shard"):
        data.load_sequence(tmp_path / "y.npz")


def test_cli_generate_and_show(tmp_path):
    run = [sys.executable, "-m", "completion.data"]
    out = subprocess.run(
        run
        + [
            "generate",
            "--condition",
            "slide_behind",
            "--split",
            "test",
            "--count",
            "1",
            "--views",
            "3",
            "--out",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "1 sequences" in out.stdout
    shard = tmp_path / "slide_behind_test_s0_00000.npz"
    png = tmp_path / "v.png"
    subprocess.run(run + ["show", str(shard), "--out", str(png)], check=True, capture_output=True)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    bad = subprocess.run(
        run
        + [
            "generate",
            "--condition",
            "nope",
            "--split",
            "train",
            "--count",
            "1",
            "--out",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "comma-separated list of conditions" in bad.stderr
