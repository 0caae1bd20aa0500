"""``python -m grasp.evaluate``: the command line, and :func:`evaluate`, the whole run."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

from completion.cli import HelpWithDefaults, integer_at_least, name_list
from completion.objects import load_object, objects_in_folder
from completion.prior import PRIOR_FILE
from completion.scenes import CONDITIONS, VIEWS
from grasp.evaluate.config import (
    MEASURED,
    MEASURED_ON,
    PRESETS,
    PRIOR,
    ROWS,
    Preset,
    Settings,
    checkpoints_loaded,
)
from grasp.evaluate.figures import write_figures
from grasp.evaluate.pool import run_jobs
from grasp.evaluate.results_json import build_results
from grasp.evaluate.results_md import markdown_report
from grasp.evaluate.runner import make_jobs
from grasp.evaluate.tables import OPTIONS, Option
from grasp.evaluate.tables.base import per_preset


def _preset_help(field: str) -> str:
    """The defaults of a preset-given option, read from the presets so that --help cannot drift."""
    return per_preset(*(getattr(PRESETS[name], field) for name in ("default", "quick", "full")))


def _add(parser: argparse.ArgumentParser, option: Option) -> None:
    """A table's option: ``--<name> N`` (and ``--no-<name>`` where it has one)."""
    bare = {} if option.bare is None else {"nargs": "?", "const": option.bare}
    parser.add_argument(option.flag, type=integer_at_least(option.least), default=None,
                        metavar="N", help=option.help_text(), **bare)
    if option.negatable:
        parser.add_argument(f"--no-{option.flag[2:]}", action="store_const", const=0,
                            dest=option.name, help=f"the same as {option.flag} 0")


def evaluate(settings: Settings, *, out: Path | None = None, progress: bool = True) -> dict:
    """Run the whole evaluation; write results.json, results.md and figures when ``out``."""
    t0 = time.perf_counter()
    jobs = make_jobs(settings)
    raw = run_jobs(settings, jobs, progress=progress)
    t1 = time.perf_counter()
    wall = {"sequences": t1 - t0}
    results = build_results(raw, settings, wall)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        t2 = time.perf_counter()
        if settings.examples:
            write_figures(results, raw, out)
        results["timings_s"]["wall"]["figures"] = round(time.perf_counter() - t2, 2)
        results["timings_s"]["wall"]["total"] = round(time.perf_counter() - t0, 2)
        (out / "results.json").write_text(json.dumps(results, indent=1))
        (out / "results.md").write_text(markdown_report(results))
    else:
        results["timings_s"]["wall"]["total"] = round(time.perf_counter() - t0, 2)
    return results


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(formatter_class=HelpWithDefaults,
        prog="python -m grasp.evaluate",
        description="The paper's evaluation: Jaccard, F-score@1%/2% and grasp joint error for "
        "every model on freshly generated scenes (deterministic from --seed). With no option: "
        f"{MEASURED['default'].text} on {MEASURED_ON}.",
    )
    size = p.add_mutually_exclusive_group()
    size.add_argument(
        "--quick",
        action="store_const",
        const="quick",
        dest="preset",
        help=f"a smoke test of the whole chain ({MEASURED['quick'].text} on two free cores)",
    )
    size.add_argument(
        "--full",
        action="store_const",
        const="full",
        dest="preset",
        help="50 sequences per cell, the planner's 64 candidates (not measured; estimated at "
        "about 40 min on two cores)",
    )
    p.set_defaults(preset="default")
    _add_what_options(p)
    for option in OPTIONS.values():  # the other tables' own (tables.base.Option)
        _add(p, option)
    _add_run_options(p)
    return p


def _add_what_options(p: argparse.ArgumentParser) -> None:
    """What is evaluated: conditions, rows, meshes, and how many sequences of each."""
    p.add_argument(
        "--conditions",
        type=name_list(CONDITIONS, "conditions"),
        default=CONDITIONS,
        help="comma-separated conditions (default: all six: the paper's five and tabletop)",
    )
    p.add_argument(
        "--models",
        type=name_list(ROWS, "rows"),
        default=ROWS,
        help=f"comma-separated rows (default: all of {', '.join(ROWS)})",
    )
    p.add_argument(
        "--objects",
        type=Path,
        default=None,
        metavar="DIR",
        help="also evaluate every OBJ/STL/PLY mesh in DIR (camera pan, one sequence each; "
        "default: none)",
    )
    p.add_argument(
        "--count",
        type=integer_at_least(1),
        default=None,
        help=f"sequences per condition and split ({_preset_help('count')})",
    )
    p.add_argument(
        "--grasp-count",
        type=integer_at_least(0),
        default=None,
        help="test sequences grasped per single-object condition (the joint error's cells); "
        "beyond --count, the extra test sequences are grasped only, in no completion table; "
        "the train split grasps at most --count (with --count and no --grasp-count: at most "
        f"--count in both; {_preset_help('grasp_count')})",
    )
    p.add_argument(
        "--physics-count",
        type=integer_at_least(0),
        default=None,
        metavar="N",
        help="of the grasped test sequences, how many are also lift-tested in pybullet dynamics "
        f"(grasp success; 0 = none; {_preset_help('physics_count')})",
    )


def _add_run_options(p: argparse.ArgumentParser) -> None:
    """How it runs: the planner's candidates, views, workers, seed, weights and outputs."""
    p.add_argument(
        "--candidates",
        type=integer_at_least(1),
        default=None,
        help=f"grasp planner candidates per plan ({_preset_help('candidates')})",
    )
    p.add_argument("--views", type=integer_at_least(2), default=VIEWS, help="views per sequence")
    p.add_argument(
        "--workers",
        type=integer_at_least(1),
        default=None,
        help="worker processes, or Ray actors with --ray (default: the CPUs this process may "
        "use)",
    )
    p.add_argument(
        "--ray",
        action="store_true",
        help="run the workers on Ray: the cluster at RAY_ADDRESS, else a local runtime "
        "(pip install -e '.[cluster]'); the same tables as without",
    )
    p.add_argument("--seed", type=int, default=0, help="one seed for scenes, samples and grasps")
    p.add_argument(
        "--weights",
        type=Path,
        default=None,
        metavar="DIR",
        help="folder of <model>.pt checkpoints (default: completion/weights/)",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=Path("evaluation"),
        metavar="DIR",
        help="where results.json, results.md and the figures go (default: evaluation/)",
    )
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def settings_from_args(args: argparse.Namespace, parser: argparse.ArgumentParser) -> Settings:
    from completion.model import WEIGHTS_DIR

    preset = PRESETS[args.preset]
    weights = args.weights if args.weights is not None else WEIGHTS_DIR
    paths = []
    for name in checkpoints_loaded(args.models):
        path = Path(weights) / f"{name}.pt"
        if not path.is_file():
            train = f"python -m completion.train --model {name} --out {path}"
            if name in ("mvp3", "mvp6"):
                train = f"python -m completion.train --model {name} --views {name[-1]} --out {path}"
            parser.exit(
                2,
                f"{parser.prog}: error: missing weights for model {name!r}: {path} "
                f"does not exist. Train them with `{train}` (see "
                "completion/weights/README.md), pass --weights DIR, or leave the "
                f"model out with --models.\n",
            )
        paths.append((name, str(path)))
    objects: tuple[str, ...] = ()
    if args.objects is not None:
        try:
            objects = tuple(objects_in_folder(args.objects))
            for object_id in objects:
                load_object(object_id)  # unreadable meshes fail here, not in a worker
        except ValueError as exc:
            parser.error(f"--objects: {exc}")
    workers = args.workers
    if workers is None:
        workers = (
            len(os.sched_getaffinity(0))
            if hasattr(os, "sched_getaffinity")
            else (os.cpu_count() or 1)
        )
    prior_path = Path(weights) / PRIOR_FILE
    if PRIOR in args.models and not prior_path.is_file():
        parser.exit(
            2,
            f"{parser.prog}: error: missing the prior row's file {prior_path}. Build it with "
            f"`python -m completion.prior --out {prior_path}`, pass --weights DIR, or leave "
            "the row out with --models.\n",
        )
    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(Preset)
             if getattr(args, f.name) is not None}
    if "count" in given and "grasp_count" not in given:  # grasp no more than is counted
        given["grasp_count"] = min(given["count"], preset.grasp_count)
    sizes = dataclasses.replace(preset, **given)
    return Settings(
        **dataclasses.asdict(sizes),
        options=tuple((name, _option_value(args, option)) for name, option in OPTIONS.items()),
        rows=tuple(args.models),
        model_paths=tuple(paths),
        prior_path=str(prior_path) if PRIOR in args.models else "",
        conditions=tuple(args.conditions),
        objects=objects,
        views=args.views,
        seed=args.seed,
        workers=workers,
        ray=args.ray,
        examples=not args.no_figures,
    )


def _option_value(args: argparse.Namespace, option: Option) -> int:
    """What the command line gives a table's option, else the option it follows when that one is
    given, else its value in the run's preset."""
    given = getattr(args, option.name)
    if given is None and option.follows is not None:
        given = getattr(args, option.follows)
    return option.preset(args.preset) if given is None else given


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    settings = settings_from_args(args, parser)
    results = evaluate(settings, out=args.out, progress=not args.quiet)
    print(markdown_report(results))
    figures = "" if args.no_figures else " and the figures"
    print(f"wrote {args.out / 'results.json'}, {args.out / 'results.md'}{figures}")
    return 0

