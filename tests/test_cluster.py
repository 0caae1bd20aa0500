"""``--ray``: data generation and evaluation on a local Ray runtime equal the process pool.

Ray is the optional ``cluster`` extra; CI installs it with the tests (the README's test command),
so these tests run there and never skip.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from completion import data
from completion.cluster import ray_map

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True, scope="module")
def _ray_down_afterwards():
    """The in-process tests start a local Ray runtime; stop it before the other test files."""
    yield
    import ray

    ray.shutdown()


def test_ray_map_keeps_the_order():
    items = [(-1) ** k * k for k in range(12)]  # builtins: a worker imports nothing of the tests
    assert list(ray_map(abs, items, workers=2)) == [abs(x) for x in items]


def test_data_generation_on_ray_writes_the_same_shards(tmp_path):
    kwargs = dict(seed=4, views=3, progress=False, workers=2)
    pool = data.generate(["camera_pan", "slide_behind"], "val", 2, out=tmp_path / "pool", **kwargs)
    ray = data.generate(["camera_pan", "slide_behind"], "val", 2, out=tmp_path / "ray", ray=True,
                        **kwargs)  # fmt: skip
    assert [p.name for p in pool] == [p.name for p in ray]
    for a, b in zip(pool, ray, strict=True):
        sa, sb = data.load_sequence(a), data.load_sequence(b)
        for key in data.SHARD_KEYS:
            np.testing.assert_array_equal(getattr(sa, key), getattr(sb, key))
        assert sa.meta == sb.meta


@pytest.mark.slow
def test_an_evaluation_on_ray_gives_the_same_tables(tmp_path):
    """Every kind of job (the main table's grasped and lift-tested sequences, a named object, the
    benchmark, the clutter table) on the shipped models, on Ray actors and on the process pool."""
    small = ["--conditions", "camera_pan,tabletop", "--count", "1", "--grasp-count", "1",
             "--physics-count", "1", "--candidates", "4", "--named", "1", "--sensor", "0",
             "--overhead", "0", "--benchmark", "1", "--benchmark-candidates", "8", "--clutter", "1"]
    results = {}
    for name, extra in (("pool", []), ("ray", ["--ray"])):
        out = tmp_path / name
        done = subprocess.run(
            [sys.executable, "-m", "grasp.evaluate", *small, "--workers", "2", "--no-figures",
             "--quiet", "--out", str(out), *extra],
            cwd=REPO, capture_output=True, text=True, timeout=1200,
        )  # fmt: skip
        assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
        results[name] = json.loads((out / "results.json").read_text())
    pool, ray = results["pool"], results["ray"]
    assert ray["config"]["ray"] and not pool["config"]["ray"]
    for key in ("tables", "counts", "fscore_ceiling", "grasp_success_counts", "grasp_failures",
                "per_view_jaccard", "named_objects", "per_object"):
        assert ray[key] == pool[key], key
    assert "Ray actors" in (tmp_path / "ray" / "results.md").read_text()
