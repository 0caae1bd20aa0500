"""grasp.evaluate: the fusion reference, the command line, and a tiny end-to-end run."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from completion.cli import name_list
from completion.config import ModelConfig
from completion.grid import GRID_SHAPE
from completion.model import WEIGHTS_DIR, build_model, save_checkpoint
from completion.scenes import CONDITIONS, SINGLE_OBJECT_CONDITIONS
from grasp import evaluate as ev
from grasp.evaluate.aggregate import aggregate
from grasp.evaluate.runner import Evaluator
from grasp.evaluate.sequence_result import SequenceResult
from hands.barrett import JOINT_NAMES

ROOT = Path(__file__).resolve().parents[1]
PRIOR_PATH = str(WEIGHTS_DIR / "prior.npz")

TINY = {"channels": (2, 2, 2), "embed_dim": 8, "n_heads": 2, "n_features": 8}
KINDS = {
    "single_view": "single_view",
    "mvp": "mvp",
    "mvt": "mvt",
    "lstm": "lstm",
    "mvp3": "mvp",
    "mvp6": "mvp",
    "mvp_posed": "mvp",  # with registered_input (_tiny_weights)
}


def _tiny_weights(folder, *, logit: float | None = 2.0) -> dict[str, str]:
    """Untrained tiny checkpoints whose output is a constant logit (a full grid at 0.5).

    An untrained network predicts noise around 0.5, whose marching-cubes surface is a sponge;
    a constant, well-defined completion keeps the test fast and every metric defined.
    ``logit=None`` keeps the untrained network as it is.
    """
    paths = {}
    for i, (name, kind) in enumerate(KINDS.items()):
        model = build_model(ModelConfig(kind=kind, seed=i, registered_input=name == "mvp_posed",
                                        **TINY))
        last = model.decoder.out
        if logit is not None:
            with torch.no_grad():
                last.weight.zero_()
                last.bias.fill_(logit)
        path = folder / f"{name}.pt"
        save_checkpoint(model, path, threshold=0.5)
        paths[name] = str(path)
    shutil.copy(PRIOR_PATH, folder / "prior.npz")  # the prior row's shipped file
    return paths


# ------------------------------------------------------------------------------ fusion reference


def test_registered_fusion_maps_observed_voxels_with_the_camera_poses():
    pitch = 0.01
    g2c = np.eye(4)
    g2c[:3, :3] *= pitch
    inputs = np.zeros((2, *GRID_SHAPE), dtype=bool)
    inputs[0, 10, 11, 12] = True
    inputs[1, 30, 30, 30] = True
    cameras = np.stack([np.eye(4), np.eye(4)])
    cameras[1, 0, 3] = 2 * pitch  # the second camera moved 2 voxels along its x axis
    fused = ev.registered_fusion(inputs, np.stack([g2c, g2c]), cameras)
    np.testing.assert_array_equal(fused[0], inputs[0])
    expected = inputs[1].copy()
    expected[8, 11, 12] = True  # seen from 2 voxels further right, it appears 2 voxels left
    np.testing.assert_array_equal(fused[1], expected)


# ------------------------------------------------------------------------------ command line


def test_bad_command_line_input_says_what_was_expected(capsys):
    for argv, expected in (
        (["--conditions", "camera_pan,nope"], "comma-separated list of conditions"),
        (["--models", "mvp,gpt"], "comma-separated list of rows"),
        (["--count", "0"], "integer >= 1"),
        (["--workers", "two"], "expected an integer"),
        (["--quick", "--full"], "not allowed with argument"),
        (["--physics-count", "-1"], "integer >= 0"),
        (["--physics-count", "some"], "expected an integer"),
    ):
        with pytest.raises(SystemExit) as exc:
            ev.main(argv)
        assert exc.value.code == 2
        assert expected in capsys.readouterr().err


def test_names_are_accepted_as_the_tables_print_them():
    models = name_list(ev.ROWS, "rows")
    assert models("MVP,Single-View, registered fusion") == ("mvp", "single_view",
                                                            "registered_fusion")
    assert name_list(ev.CONDITIONS, "conditions")("Camera Pan") == ("camera_pan",)


def test_missing_weights_name_the_file_and_the_train_command(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        ev.main(["--weights", str(tmp_path), "--models", "mvp3,registered_fusion"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert str(tmp_path / "mvp3.pt") in err
    assert "python -m completion.train --model mvp3 --views 3" in err


def test_objects_folder_without_meshes_is_an_argparse_error(tmp_path, capsys):
    with pytest.raises(SystemExit):
        ev.main(["--models", "registered_fusion", "--objects", str(tmp_path)])
    assert "no OBJ/STL/PLY meshes" in capsys.readouterr().err
    (tmp_path / "broken.obj").write_text("this is not a mesh\n")
    with pytest.raises(SystemExit):
        ev.main(["--models", "registered_fusion", "--objects", str(tmp_path)])
    assert "broken.obj" in capsys.readouterr().err


# ------------------------------------------------------------------------------ end to end


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    pytest.importorskip("grasp.planner", reason="grasp.planner is not written yet")
    root = tmp_path_factory.mktemp("evaluate")
    weights = root / "weights"
    _tiny_weights(weights)
    objects = root / "objects"
    objects.mkdir()
    trimesh.creation.box((0.06, 0.05, 0.08)).export(objects / "box.stl")
    out = root / "out"
    argv = [
        "--weights", str(weights), "--objects", str(objects), "--count", "1",
        "--grasp-count", "1", "--physics-count", "1", "--named", "1",
        "--overhead", "4",  # tabletop test index 3 of seed 3 is seen from 81°
        "--benchmark", "1", "--benchmark-candidates", "8", "--clutter", "1",
        "--sensor", "1",  # one sequence per paper condition through the sensor model
        "--views", "3", "--candidates", "2", "--workers", "1", "--quiet",
        "--out", str(out), "--seed", "3",
    ]
    assert ev.main(argv) == 0
    return out, json.loads((out / "results.json").read_text())


def test_tiny_run_fills_every_cell_that_applies(tiny_run):
    out, results = tiny_run
    tables = results["tables"]
    assert set(tables) >= {"jaccard", "fscore_1", "fscore_2", "joint_error_deg"}
    for metric in ("jaccard", "fscore_1", "fscore_2"):
        assert set(tables[metric]) == set(ev.ROWS)
        for row in ev.ROWS:
            for condition in CONDITIONS:
                for split in ("train", "test"):
                    value = tables[metric][row][condition][split]
                    assert value is not None and 0.0 <= value <= 1.0, (metric, row, condition)
    for row in ev.ROWS:
        for condition in CONDITIONS:
            for split in ("train", "test"):
                value = tables["joint_error_deg"][row][condition][split]
                counts = results["counts"][row][condition][split]
                if condition in SINGLE_OBJECT_CONDITIONS:
                    assert counts["grasped"] == 1
                    assert value is not None and value >= 0.0, (row, condition, split)
                else:
                    assert value is None and counts["grasped"] == 0
    per_joint = results["joint_error_per_joint_deg"]
    assert set(per_joint["mvp"]["camera_pan"]["test"]) == set(JOINT_NAMES)
    assert per_joint["mvp"]["two_object_pan"]["test"] is None
    assert set(results["pooled_joint_error_per_joint_deg"][ev.FUSION]) == set(JOINT_NAMES)
    for key in ("named_objects", "objects_dir"):
        block = results[key]
        assert len(block["objects"]) == 1
        for metric in ("jaccard", "fscore_1", "fscore_2", "joint_error_deg"):
            assert all(block["tables"][metric][row] is not None for row in ev.ROWS), (key, metric)
    assert results["objects_dir"]["objects"][0].endswith("box.stl")
    success = tables["grasp_success"]
    assert set(success) == {*ev.ROWS, ev.TRUE_MESH}
    for row in success:
        for condition in CONDITIONS:
            for split in ("train", "test"):
                value = success[row][condition][split]
                n = results["grasp_success_counts"][row][condition][split]
                if condition in SINGLE_OBJECT_CONDITIONS and split == "test":  # test only
                    assert n["tested"] == 1 and value in (0.0, 1.0), (row, condition, split)
                    assert value == n["held"] / n["tested"]
                else:
                    assert value is None and n["tested"] == 0, (row, condition, split)


def test_tiny_run_writes_its_reports(tiny_run):
    out, results = tiny_run
    for name in (
        "results.json",
        "results.md",
        "jaccard_per_view.png",
        "examples.png",
        "grasps.png",
    ):
        assert (out / name).stat().st_size > 0, name
    report = (out / "results.md").read_text()
    assert "Table I: Jaccard" in report and "Registered fusion" in report
    assert "Grasp success" in report and "True mesh (planned on the truth)" in report
    # a run of fewer than 5 sequences per cell is a smoke test: it says so and bolds nothing
    assert results["config"]["count"] < 5 and "**A smoke test**" in report
    ours = report.split("Table I: Jaccard", 1)[1].split("The paper's numbers", 1)[0]
    assert not [line for line in ours.splitlines() if line.startswith("|") and "**" in line]
    assert results["config"]["views"] == 3 and results["config"]["seed"] == 3
    assert "Prior, ignores the input" in report and "How to read this" in report
    for condition in CONDITIONS:
        ceiling = results["fscore_ceiling"][condition]
        assert 0.0 < ceiling["fscore_1"] <= ceiling["fscore_2"] <= 1.0, condition
    moving = results["tables"]["joint_error_moving_deg"]["mvp"]["camera_pan"]["test"]
    assert moving == pytest.approx(results["tables"]["joint_error_deg"]["mvp"]["camera_pan"]
                                   ["test"] * 4 / 3, abs=1e-3)  # the spreads never differ
    per_view = results["per_view_jaccard"]["mvp"]["object_hiding"]["test"]
    assert len(per_view) == 3
    # the first view has no memory to draw on: MVP and its memory-off row see the same thing
    for condition in CONDITIONS:
        for split in ("train", "test"):
            views = results["per_view_jaccard"]
            assert views[ev.MEMORY_OFF][condition][split][0] == pytest.approx(
                views["mvp"][condition][split][0], abs=1e-6), condition
    assert "MVP, memory off" in report
    sensor, main = results["sensor_noise"], results["tables"]["jaccard"]
    for row in ev.ROWS:
        for c in CONDITIONS:  # each condition on and off, the same sequences, one side the main's
            on, off = sensor["jaccard"][row][c]["mean"], sensor["noiseless"][row][c]["mean"]
            assert sensor["n"][row][c] == 1 and 0.0 <= min(on, off) <= max(on, off) <= 1.0
            assert sensor["difference"][row][c]["mean"] == pytest.approx(on - off, abs=2e-4)
            side = on if c == "tabletop" else off  # tabletop is seen through the sensor by default
            assert side == pytest.approx(main[row][c]["test"], abs=1e-4)
    overhead = results["tabletop_overhead"]
    assert overhead["searched"] == 4 and overhead["views"] >= 3 and overhead["sequences"] >= 1
    for row in ev.ROWS:
        assert 0.0 <= overhead["below_plane_share"][row] <= 1.0
    assert 0.0 <= overhead["target_below_plane_share"] < 0.1
    assert "with the sensor model on" in report and "Tabletop seen from above" in report
    bench = results["grasp_benchmark"]
    assert list(bench) == ["true_mesh", "mvp_1view", "mvp_4views", "mvp_4views_memory",
                           "single_view_1view", "registered_fusion_4views", "true_mesh_verified",
                           "mvp_1view_verified", "mvp_4views_verified"]
    assert "Verified rows" in report and "trials held, referee held" in report
    for cell in bench.values():
        assert cell["tested"] == 1 and sum(cell["reasons"].values()) == 1 - cell["held"]
        assert 0 <= cell["ci95"][0] <= cell["held"] <= cell["ci95"][1] <= 1
    (record,) = results["grasp_benchmark_objects"]
    assert record["id"] == "named/mug" and "on a table" in report
    assert len(record["size_m"]) == 3 and record["mass_kg"] > 0
    assert set(record["rows"]) == set(bench)
    for outcome in record["rows"].values():
        assert isinstance(outcome["held"], bool) and outcome["reason"]
        if "executed_joints_deg" in outcome:  # a grasp was planned and executed
            assert len(outcome["planned_joints_deg"]) == len(outcome["executed_joints_deg"]) == 8
    for row, outcome in record["rows"].items():  # what the verification saw of the top grasp
        if row.endswith("_verified") and "executed_joints_deg" in outcome:
            assert set(outcome["verification"]) == {"tried", "trials", "held", "first_drop"}
            assert 0 <= outcome["tried"] <= 4
            assert outcome["kind"].split(", ")[0] in ("power", "fingertip")
    records = [r for r in results["per_object"] if r["table"] == "main"]
    assert len(records) == len(CONDITIONS) * 2 * len(ev.ROWS)
    for kind in ("wall", "cpu"):
        stages = results["timings_s"][f"stages_{kind}_summed_over_sequences"]
        assert set(stages) == {
            "generation",
            "inference",
            "completion_metrics",
            "grasping",
            "physics",
            "benchmark",
            "clutter",
        }
        assert all(v >= 0 for v in stages.values()) and stages["grasping"] > 0
        assert stages["physics"] > 0
    # the clutter table: one scene, every row (the tiny MVP's completions included)
    clutter = results["clutter"]
    assert set(clutter) == {"true_meshes", "mvp_4views_obstacles", "mvp_4views_ignoring"}
    assert all(cell["tested"] == 1 and 0 <= cell["success"] <= cell["held"] <= 1
               for cell in clutter.values())
    [scene] = results["clutter_scenes"]
    assert 2 <= len(scene["neighbours"]) <= 5 and all(0.02 <= g <= 0.1 for g in scene["gaps_m"])
    assert "Grasp success in clutter" in (out / "results.md").read_text()


def test_same_seed_same_numbers(tiny_run, tmp_path):
    """A second run of one cell reproduces the first run's numbers exactly."""
    _, first = tiny_run
    weights = tmp_path / "weights"
    paths = _tiny_weights(weights)
    settings = ev.Settings(
        rows=("mvp", ev.FUSION),
        model_paths=(("mvp", paths["mvp"]),),
        conditions=("object_hiding",),
        count=1,
        grasp_count=0,
        options=(("named", 0), ("sensor", 0), ("benchmark", 0), ("clutter", 0)),  # one cell
        views=3,
        seed=3,
        candidates=2,
        examples=False,
    )
    again = ev.evaluate(settings, progress=False)
    for metric in ("jaccard", "fscore_1"):
        for row in ("mvp", ev.FUSION):
            assert (
                again["tables"][metric][row]["object_hiding"]
                == first["tables"][metric][row]["object_hiding"]
            )


def test_numbers_do_not_depend_on_the_number_of_workers(tmp_path):
    paths = _tiny_weights(tmp_path, logit=None)  # untrained: outputs scattered around 0.5
    runs = []
    for workers in (1, 2):
        settings = ev.Settings(
            rows=("mvp", ev.FUSION),
            model_paths=(("mvp", paths["mvp"]),),
            conditions=("object_reveal",),
            count=1,
            grasp_count=0,
            # the benchmark's records are compared too (per_object)
            options=(("named", 0), ("sensor", 1), ("benchmark", 2), ("benchmark_candidates", 8),
                     ("clutter", 1)),
            views=3,
            seed=5,
            workers=workers,
            examples=False,
        )
        runs.append(ev.evaluate(settings, progress=False))
    assert runs[0]["per_object"] == runs[1]["per_object"]
    assert runs[0]["tables"] == runs[1]["tables"]


# ------------------------------------------------------------------------------ trust


def _settings(paths: dict, **changes) -> ev.Settings:
    base = dict(
        rows=("mvp", ev.PRIOR, ev.FUSION),
        model_paths=(("mvp", paths["mvp"]),),
        prior_path=PRIOR_PATH,
        conditions=("camera_pan",),
        count=1,
        grasp_count=0,
        # the main table's rows are what these tests look at
        options=(("named", 0), ("sensor", 0), ("overhead", 0), ("clutter", 0), ("benchmark", 0)),
        views=3,
        seed=7,
        candidates=2,
        examples=False,
    )
    return ev.Settings(**(base | changes))


class _GroundTruthAsModel(Evaluator):
    """The mvp row answers with the 40³ target itself: a perfect completion."""

    def probabilities(self, seq):
        out = super().probabilities(seq)
        out["mvp"] = seq.targets.astype(np.float32)
        return out


def test_ground_truth_scores_jaccard_one_and_the_fscore_ceiling(tmp_path):
    paths = _tiny_weights(tmp_path)
    evaluator = _GroundTruthAsModel(_settings(paths))
    try:
        for condition in ("camera_pan", "object_hiding", "two_object_pan"):
            result = evaluator.evaluate(ev.Job(ev.MAIN_TABLE, condition, "test", 0))
            assert result.per_view["mvp"]["jaccard"] == [1.0, 1.0, 1.0]
            for m in ("fscore_1", "fscore_2"):
                assert result.per_view["mvp"][m] == result.ceiling[m], (condition, m)
                assert all(0.5 < f <= 1.0 for f in result.ceiling[m])
    finally:
        evaluator.close()


def test_prior_row_does_not_change_when_every_input_is_zeroed(tmp_path, monkeypatch):
    import completion.scenes

    paths = _tiny_weights(tmp_path, logit=None)
    settings = _settings(paths, conditions=("object_hiding", "slide_behind"))
    first = ev.evaluate(settings, progress=False)
    make_sequence = completion.scenes.make_sequence

    def blind(*args, **kwargs):
        seq = make_sequence(*args, **kwargs)
        seq.inputs[:] = False
        return seq

    monkeypatch.setattr(completion.scenes, "make_sequence", blind)
    second = ev.evaluate(settings, progress=False)
    for metric in ("jaccard", "fscore_1", "fscore_2"):
        assert second["tables"][metric][ev.PRIOR] == first["tables"][metric][ev.PRIOR]
    # the fusion row does look at the input: zeroed, it has nothing left
    assert second["tables"]["jaccard"][ev.FUSION] != first["tables"]["jaccard"][ev.FUSION]


def _record(condition, split, index, jaccard, *, grasp=None, lift=None, ceiling=0.9):
    """A hand-made SequenceResult of one row ("mvp") with 2 views."""
    job = ev.Job(ev.MAIN_TABLE, condition, split, index, grasp=grasp is not None)
    per_view = {"mvp": {"jaccard": jaccard, "fscore_1": [0.5, 0.7], "fscore_2": [0.6, 0.8]}}
    grasps = {} if grasp is None else {"mvp": grasp}
    physics = {} if lift is None else {"mvp": {"success": lift}, ev.TRUE_MESH: {"success": True}}
    result = SequenceResult(job, ["proc/box/1"], per_view, grasps, physics=physics)
    result.ceiling = {"fscore_1": [ceiling, ceiling], "fscore_2": [1.0, 1.0]}
    return result


def _grasp(per_joint):
    if per_joint is None:
        return {"error_deg": None, "error_moving_deg": None, "per_joint_deg": None,
                "reason": "empty completion: no surface to plan on"}
    moving = [v for v, name in zip(per_joint, JOINT_NAMES, strict=True) if "spread" not in name]
    return {"error_deg": float(np.mean(per_joint)), "error_moving_deg": float(np.mean(moving)),
            "per_joint_deg": per_joint, "reason": ""}


def test_aggregation_of_hand_made_records_gives_hand_computed_cells():
    joints_a = [0, 2, 4, 0, 6, 8, 10, 12]  # spreads first in each finger: 8-mean 5.25, 6-mean 7
    joints_b = [0, 1, 1, 0, 1, 1, 1, 1]  # 8-mean 0.75, 6-mean 1
    results = [
        _record("camera_pan", "test", 0, [1.0, 0.5], grasp=_grasp(joints_a), lift=True),
        _record("camera_pan", "test", 1, [0.0, 0.5], grasp=_grasp(joints_b), lift=False),
        _record("camera_pan", "test", 2, [0.2, 0.2], grasp=_grasp(None), lift=False,
                ceiling=0.6),
        _record("two_object_pan", "train", 0, [0.4, 0.6]),
    ]
    settings = ev.Settings(rows=("mvp",), model_paths=(("mvp", "unused.pt"),))
    agg = aggregate(results, settings, ev.MAIN_TABLE)
    t = agg["tables"]
    assert t["jaccard"]["mvp"]["camera_pan"]["test"] == pytest.approx((0.75 + 0.25 + 0.2) / 3,
                                                                      abs=1e-4)
    assert t["jaccard"]["mvp"]["two_object_pan"]["train"] == 0.5
    assert t["fscore_1"]["mvp"]["camera_pan"]["test"] == 0.6
    # the failed grasp is counted in the cell, not averaged in
    assert t["joint_error_deg"]["mvp"]["camera_pan"]["test"] == pytest.approx(3.0)
    assert t["joint_error_moving_deg"]["mvp"]["camera_pan"]["test"] == pytest.approx(4.0)
    assert agg["counts"]["mvp"]["camera_pan"]["test"] == {"sequences": 3, "grasped": 3,
                                                          "grasp_ok": 2}
    assert agg["grasp_failures"]["mvp"]["camera_pan"]["test"] == [
        "empty completion: no surface to plan on"
    ]
    assert t["joint_error_deg"]["mvp"]["two_object_pan"]["train"] is None
    assert t["grasp_success"]["mvp"]["camera_pan"]["test"] == pytest.approx(1 / 3, abs=1e-4)
    assert agg["grasp_success_counts"]["mvp"]["camera_pan"]["test"] == {"tested": 3, "held": 1}
    assert t["grasp_success"][ev.TRUE_MESH]["camera_pan"]["test"] == 1.0
    assert agg["ceiling"]["camera_pan"]["test"]["fscore_1"] == pytest.approx(0.8)
    assert agg["per_view_jaccard"]["mvp"]["camera_pan"]["test"] == pytest.approx([0.4, 0.4])
    report = ev.markdown_report(ev.build_results(results, settings, {"sequences": 1.0}))
    assert "3.00° (2/3)" in report and "4.00° (2/3)" in report  # cells say what they average
    assert "Ceiling" in report and "How to read this" in report


def test_jaccard_precision_gives_standard_errors_paired_differences_and_the_rise():
    def record(index, mvp, single_view):
        job = ev.Job(ev.MAIN_TABLE, "camera_pan", "test", index, grasp=False)
        per_view = {row: {"jaccard": j, "fscore_1": [0.0] * 6, "fscore_2": [0.0] * 6}
                    for row, j in (("mvp", mvp), ("single_view", single_view))}
        result = SequenceResult(job, ["proc/box/1"], per_view, {})
        result.ceiling = {"fscore_1": [1.0], "fscore_2": [1.0]}
        return result

    results = [
        record(0, [0.5, 0.5, 0.5, 0.8, 0.8, 0.8], [0.4] * 6),  # mean 0.65, +0.25, rise +0.3
        record(1, [0.3] * 6, [0.1] * 6),  # mean 0.3, +0.2, rise 0
    ]
    settings = ev.Settings(rows=("single_view", "mvp"),
                           model_paths=(("single_view", "a.pt"), ("mvp", "b.pt")))
    p = aggregate(results, settings, ev.MAIN_TABLE)["jaccard_precision"]
    mvp = p["mvp"]["camera_pan"]["test"]
    assert mvp["cell"] == {"mean": 0.475, "se": pytest.approx(0.175, abs=1e-4), "n": 2}
    assert mvp["vs_single_view"]["mean"] == pytest.approx(0.225)
    assert mvp["vs_single_view"]["se"] == pytest.approx(0.025, abs=1e-4)
    assert mvp["rise"]["mean"] == pytest.approx(0.15)
    assert mvp["rise"]["se"] == pytest.approx(0.15, abs=1e-4)
    assert mvp["rise_vs_single_view"]["mean"] == pytest.approx(0.15)  # Single-View is flat
    assert p["single_view"]["camera_pan"]["test"]["vs_single_view"] is None
    report = ev.markdown_report(ev.build_results(results, settings, {"sequences": 1.0}))
    assert "| MVP | 0.475 ± 0.175 |" in report
    assert "| MVP | +0.225 ± 0.025 |" in report and "| MVP | +0.150 ± 0.150 |" in report
    assert "vs_memory_off" not in mvp and "What the memory adds" not in report


def test_memory_off_row_pairs_mvp_with_itself_view_by_view():
    def record(index, mvp, off):
        job = ev.Job(ev.MAIN_TABLE, "camera_pan", "test", index, grasp=False)
        per_view = {row: {"jaccard": j, "fscore_1": [0.0] * 6, "fscore_2": [0.0] * 6}
                    for row, j in (("mvp", mvp), (ev.MEMORY_OFF, off))}
        result = SequenceResult(job, ["proc/box/1"], per_view, {})
        result.ceiling = {"fscore_1": [1.0], "fscore_2": [1.0]}
        return result

    results = [
        record(0, [0.5, 0.5, 0.5, 0.8, 0.8, 0.8], [0.5] * 6),  # +0.15, rise +0.3
        record(1, [0.3] * 6, [0.3] * 6),  # memory adds nothing
    ]
    settings = ev.Settings(rows=("mvp", ev.MEMORY_OFF), model_paths=(("mvp", "b.pt"),))
    mvp = aggregate(results, settings, ev.MAIN_TABLE)["jaccard_precision"]["mvp"]["camera_pan"]
    assert mvp["test"]["vs_memory_off"]["mean"] == pytest.approx(0.075)
    assert mvp["test"]["rise_vs_memory_off"]["mean"] == pytest.approx(0.15)
    report = ev.markdown_report(ev.build_results(results, settings, {"sequences": 1.0}))
    assert "What the memory adds" in report and "| Rise | +0.150 ± 0.150 |" in report
    with pytest.raises(ValueError, match="mvp"):  # the row runs the MVP checkpoint
        ev.Settings(rows=(ev.MEMORY_OFF,), model_paths=())


def test_nothing_prints_pybullet_noise(tmp_path):
    """pybullet's "argv[0]=" and build banner never reach stdout (or stderr)."""
    commands = [
        [sys.executable, "-m", "completion.data", "generate", "--condition", "camera_pan",
         "--split", "train", "--count", "1", "--views", "2", "--out", str(tmp_path / "data")],
        [sys.executable, "-m", "grasp.evaluate", "--models", "prior,registered_fusion",
         "--conditions", "camera_pan", "--count", "1", "--grasp-count", "1",
         "--physics-count", "1", "--named", "0", "--views", "2", "--candidates", "2",
         "--benchmark", "1", "--benchmark-candidates", "8", "--clutter", "0", "--sensor", "0",
         "--workers", "1", "--no-figures", "--quiet", "--out", str(tmp_path / "eval")],
    ]
    for command in commands:
        run = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, run.stderr
        for stream in (run.stdout, run.stderr):
            assert "argv[0]=" not in stream and "pybullet build time" not in stream, command
    assert "and the figures" not in run.stdout  # --no-figures says so


def test_grasp_summary_keeps_a_pose_the_figure_can_re_run():
    """results.json once rounded poses to 1e-6; a rounded rotation can fail the simulator's
    rigidity check (this crashed the figures once), so the summary keeps the pose whole."""
    from scipy.spatial.transform import Rotation

    from grasp.evaluate.figures import _grasp_result
    from grasp.evaluate.metrics import JointError
    from grasp.hand.collision import check_pose
    from grasp.hand.result import GraspResult, HandDofs, HandJoints

    fragile = None
    for seed in range(200):
        pose = np.eye(4)
        pose[:3, :3] = Rotation.random(random_state=seed).as_matrix()
        pose[:3, 3] = (0.1, -0.2, 0.3)
        try:
            check_pose(pose.round(6))
        except ValueError:
            fragile = pose
            break
    assert fragile is not None, "no rotation whose rounding breaks rigidity: the test is void"
    grasp = GraspResult(True, "", fragile, HandJoints(*[0.0] * 8), HandDofs(0.0, 0.0, 0.0, 0.0))
    summary = JointError(1.0, planned=grasp).as_dict()["planned"]
    fixed = _grasp_result(summary).palm_pose
    check_pose(fixed)
    np.testing.assert_allclose(fixed, fragile, atol=2e-6)


def test_timings_header_names_the_workers_in_plain_english():
    from grasp.evaluate.results_md import markdown_timings

    stages = {"generation": 1.0, "inference": 2.0}
    timings = {"stages_wall_summed_over_sequences": stages,
               "stages_cpu_summed_over_sequences": stages,
               "wall": {"sequences": 3.0, "figures": 0.5, "total": 3.5}}
    for workers, ray, header in ((2, False, "2 worker processes"), (1, False, "1 worker process)"),
                                 (3, True, "3 Ray actors")):
        text = markdown_timings({"timings_s": timings, "config": {"workers": workers, "ray": ray}})
        assert header in text.splitlines()[0]


def test_truth_meshes_are_the_objects_the_targets_were_voxelized_from():
    """The F-score's truth surface: each object scaled as its scene scaled it (two-object pan
    shrinks a pair into a 0.3 m cube, slide behind shrinks the sliding object)."""
    from completion import grid
    from completion.scenes import make_sequence, object_meshes_in_camera

    scaled = set()
    for condition in CONDITIONS:
        for index in range(4):
            seq = make_sequence(condition, "test", index, 0, views=2)
            scaled |= {condition for s in seq.meta["object_scale"] if s < 1}
            for view in range(len(seq)):
                occ = np.zeros(GRID_SHAPE, bool)
                for mesh in object_meshes_in_camera(seq, view):
                    occ |= grid.voxelize_mesh(mesh.vertices, mesh.faces, seq.grid_to_camera[view])
                target = seq.targets[view]
                overlap = (occ & target).sum() / (occ | target).sum()
                assert overlap > 0.98, (condition, index, view, overlap)
    assert scaled == {"two_object_pan", "slide_behind"}  # the case is exercised
