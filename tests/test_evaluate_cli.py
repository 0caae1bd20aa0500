"""python -m grasp.evaluate's command line: the sizes of a run are its preset replaced by what the
command line gives, and --help reads its defaults from the presets."""

from __future__ import annotations

import pytest

import grasp.evaluate as ev
from grasp.evaluate.tables import OPTIONS


def test_physics_count_comes_from_the_preset_or_the_command_line():
    parser = ev.build_parser()
    models = ["--models", ev.FUSION]
    for argv, expected in (
        ([], 5),
        (["--quick"], 1),
        (["--full"], 10),
        (["--physics-count", "0"], 0),
        (["--quick", "--physics-count", "3"], 3),
    ):
        args = parser.parse_args(models + argv)
        assert ev.settings_from_args(args, parser).physics_count == expected, argv
    jobs = ev.make_jobs(ev.Settings(rows=(ev.FUSION,), count=3, grasp_count=2, physics_count=5))
    main = [j for j in jobs if j.table == ev.MAIN_TABLE and j.split == "test"]
    assert [j.physics for j in main[:3]] == [True, True, False]  # grasped ones only
    assert not any(j.physics for j in jobs if j.split == "train")  # the test split's only


def test_every_size_is_the_preset_replaced_by_what_the_command_line_gives():
    parser = ev.build_parser()
    models = ["--models", ev.FUSION]
    sizes = ("count", "grasp_count", "physics_count", "candidates")  # the main table's

    def got(*argv: str) -> dict:
        settings = ev.settings_from_args(parser.parse_args([*models, *argv]), parser)
        return {name: getattr(settings, name) for name in sizes} | {
            name: option.of(settings) for name, option in OPTIONS.items()}

    def preset(name: str) -> dict:
        return {n: getattr(ev.PRESETS[name], n) for n in sizes} | {
            n: option.preset(name) for n, option in OPTIONS.items()}

    assert {"overhead", "clutter", "sensor", "named", "benchmark", "verified"} <= set(OPTIONS)
    assert got() == preset("default")
    assert got("--quick") == preset("quick")
    assert got("--full", "--named", "0", "--no-sensor", "--overhead", "3") == preset("full") | {
        "named": 0, "sensor": 0, "overhead": 3}
    assert got("--count", "3")["grasp_count"] == 3  # no more grasps than sequences counted
    assert got("--count", "3", "--grasp-count", "7")["grasp_count"] == 7
    assert got("--benchmark")["benchmark"] == got("--benchmark")["verified"] == 100
    assert got("--quick", "--benchmark", "7", "--verified", "2")["verified"] == 2
    assert got("--benchmark-candidates", "8")["benchmark_candidates"] == 8
    help_text = " ".join(parser.format_help().split())
    for option, name in (("--overhead", "overhead"), ("--named", "named"), ("--count", "count")):
        d, q, f = (OPTIONS[name].preset(p) if name in OPTIONS else getattr(ev.PRESETS[p], name)
                   for p in ("default", "quick", "full"))
        assert f"default {d}, {q} with --quick, {f} with --full" in help_text, option
    assert "--benchmark alone: 100" in help_text


def test_a_table_option_out_of_range_or_unknown_is_refused():
    with pytest.raises(ValueError, match="benchmark_candidates out of range"):
        ev.make_jobs(ev.Settings(rows=(ev.FUSION,), options=(("benchmark_candidates", 0),)))
    with pytest.raises(ValueError, match="no table has an option 'benchmarks'"):
        ev.make_jobs(ev.Settings(rows=(ev.FUSION,), options=(("benchmarks", 3),)))
    with pytest.raises(ValueError, match="an option named twice"):
        ev.make_jobs(ev.Settings(rows=(ev.FUSION,), options=(("sensor", 3), ("sensor", 0))))
    parser = ev.build_parser()
    with pytest.raises(SystemExit):
        parser.parse_args(["--benchmark-verify", "0"])
