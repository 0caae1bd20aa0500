"""python -m grasp.evaluate's command line: the sizes of a run are its preset replaced by what the
command line gives, and --help reads its defaults from the presets."""

from __future__ import annotations

import grasp.evaluate as ev
from grasp.evaluate.tables import TABLES


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
    sizes = ("count", "grasp_count", "physics_count", "named", "sensor", "benchmark",
             "candidates")
    own = {t.name: t for t in TABLES if t.sizing is not None}  # sized by their own option

    def got(*argv: str) -> dict:
        settings = ev.settings_from_args(parser.parse_args([*models, *argv]), parser)
        return {name: getattr(settings, name) for name in sizes} | {
            name: t.size(settings) for name, t in own.items()}

    def preset(name: str) -> dict:
        return {n: getattr(ev.PRESETS[name], n) for n in sizes} | {
            n: t.sizing.preset(name) for n, t in own.items()}

    assert "overhead" in own
    assert got() == preset("default")
    assert got("--quick") == preset("quick")
    assert got("--full", "--named", "0", "--no-sensor", "--overhead", "3") == preset("full") | {
        "named": 0, "sensor": 0, "overhead": 3}
    assert got("--count", "3")["grasp_count"] == 3  # no more grasps than sequences counted
    assert got("--count", "3", "--grasp-count", "7")["grasp_count"] == 7
    assert got("--benchmark")["benchmark"] == 100
    help_text = " ".join(parser.format_help().split())
    for option, name in (("--overhead", "overhead"), ("--count", "count")):
        d, q, f = (own[name].sizing.preset(p) if name in own else getattr(ev.PRESETS[p], name)
                   for p in ("default", "quick", "full"))
        assert f"default {d}, {q} with --quick, {f} with --full" in help_text, option
