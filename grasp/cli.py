"""``python -m grasp plan MESH`` and ``python -m grasp lift MESH``: plan BarrettHand grasps on a
mesh and print them; plan, then lift-test them in pybullet dynamics."""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from pathlib import Path

import trimesh

from completion.cli import HelpWithDefaults
from grasp.defaults import AUTOGRASP_BUDGET
from grasp.hand.quality import MU_RUBBER
from grasp.physics.lift import lift_test
from grasp.physics.settings import APPROACHES, DENSITY_KG_M3
from grasp.physics.verify import describe
from grasp.planner import plan
from grasp.ranking.rank import palm_touches
from grasp_client.wire import SupportPlane
from hands.barrett import JOINT_NAMES


def read_mesh_argument(parser, path, *, scale: float = 1.0) -> trimesh.Trimesh:
    """A command-line MESH (a mesh file or an object id, :func:`completion.objects.mesh_from_spec`),
    scaled; an ``argparse`` parser error when it is missing or holds no triangles."""
    from completion.objects import mesh_from_spec

    try:
        mesh = mesh_from_spec(str(path))
    except ValueError as exc:
        parser.error(f"no such mesh file or object: {exc}")
    if scale != 1.0:
        mesh.apply_scale(scale)
    return mesh


def _plane_argument(text: str) -> SupportPlane:
    try:
        return SupportPlane.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def build_parser() -> argparse.ArgumentParser:
    """The two subcommands and their options."""
    parser = argparse.ArgumentParser(prog="python -m grasp", formatter_class=HelpWithDefaults,
                                     description="Plan BarrettHand grasps on a mesh file, and "
                                     "lift-test them in pybullet.")
    commands = parser.add_subparsers(dest="command", required=True, metavar="{plan,lift}")
    planning = commands.add_parser("plan", formatter_class=HelpWithDefaults,
                                   help="plan grasps, print the best and the time taken",
                                   description="Plan BarrettHand grasps on a mesh file.")
    add = planning.add_argument
    add("mesh", type=Path, help="mesh file (OBJ, STL, PLY, ...; metres) or object id (named/mug)")
    add("--candidates", type=int, default=64, help="candidate grasps to try")
    add("--seed", type=int, default=0, help="seed of the candidates")
    add("--top-k", type=int, default=5, help="grasps to print")
    add("--scale", type=float, default=1.0, help="multiply the mesh by this")
    add("--budget", type=int, default=AUTOGRASP_BUDGET,
        help=f"candidates autograsped exactly, the screen's most promising first (0: all, no "
        f"screen; default {AUTOGRASP_BUDGET})")
    add("--verify", type=int, default=0, metavar="N",
        help="lift-test at most N of the best grasps on the mesh before answering, until one "
        "holds in every trial (0: none)")
    add("--support-plane", type=_plane_argument, default=None, metavar="NX,NY,NZ,D",
        help="the table the object rests on (default: none), n·x + d = 0 in the mesh's frame, "
        "n up: an obstacle to the hand, no approach from below")
    lifting = commands.add_parser(
        "lift", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        help="plan grasps, then lift-test them in pybullet dynamics",
        description="Plan a BarrettHand grasp on a mesh, then lift-test it in pybullet dynamics.")
    add = lifting.add_argument
    add("mesh", help="mesh file (OBJ/STL/PLY, metres) or an object id")
    add("--seed", type=int, default=0, help="planner and shake seed")
    add("--candidates", type=int, default=64, help="planner candidates")
    add("--top-k", type=int, default=1, help="lift-test the best K grasps")
    add("--lift", type=float, default=0.10, help="lift height (m)")
    add("--no-shake", action="store_true", help="lift only")
    add("--friction", type=float, default=MU_RUBBER, help="hand–object μ")
    add("--density", type=float, default=DENSITY_KG_M3, help="kg/m³")
    add("--table", action="store_true", help="the object stands on a table under its lowest "
        "point (z up): planned with it and lift-tested on it")
    add("--approach", choices=APPROACHES, default="planned",
        help="planned: to the planned pose (default); guarded: toward it, stopping at the first "
        "touch, as a robot executes a plan")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m grasp {plan,lift} MESH ...``; the exit status (lift: 1 when none held)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    return _plan(parser, args) if args.command == "plan" else _lift(parser, args)


def _plan(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """Plan, print the best grasps and the time taken."""
    if args.verify < 0:
        parser.error(f"--verify must be >= 0, got {args.verify}")
    mesh = read_mesh_argument(parser, args.mesh, scale=args.scale)
    wall, cpu = time.perf_counter(), time.process_time()
    timings: dict[str, float] = {}
    results = plan(mesh, n_candidates=args.candidates, seed=args.seed, top_k=args.top_k,
                   support_plane=args.support_plane, budget=args.budget or None,
                   verify=args.verify, timings=timings)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    print(f"{args.mesh.name}: {len(mesh.faces)} faces, {args.candidates} candidates in "
          f"{wall:.2f} s wall, {cpu:.2f} s CPU")
    names = ("setup", "screen", "autograsp", "rank") + (("verify",) if args.verify else ())
    stages = ", ".join(f"{name} {1000 * timings[name]:.0f} ms" for name in names)
    rate = timings["screened"] / timings["screen"] if timings["screened"] else 0.0
    print(f"stages: {stages}; screened {timings['screened']} ({rate:.0f} a second), "
          f"autograsped {timings['autograsped']}"
          + (f", lift-tested {timings['verified']}" if args.verify else ""))
    for rank, r in enumerate(results, 1):
        position = ", ".join(f"{1000 * v:.0f}" for v in r.palm_pose[:3, 3])
        approach = ", ".join(f"{v:+.2f}" for v in r.palm_pose[:3, 2])
        fingers = ", ".join(f"{v:+.2f}" for v in r.palm_pose[:3, 1])
        print(
            f"{rank:2d}. eps {r.epsilon:6.3f}  volume {r.volume:7.3f}  "
            f"{'palm, ' if palm_touches(r) else ''}palm at ({position}) mm, "
            f"approach ({approach}), fingers along ({fingers})  {r.reason}"
        )
        joints = zip(JOINT_NAMES, r.joints_deg, strict=True)
        print("    " + "  ".join(f"{name} {v:.1f}°" for name, v in joints))
        if r.verification is not None:
            print(f"    {describe(r.verification)}")
    return 0


def _lift(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """Plan, then lift-test the best ``--top-k`` grasps; 1 when none held."""
    mesh = read_mesh_argument(parser, args.mesh)
    plane = SupportPlane([0.0, 0.0, 1.0], -float(mesh.bounds[0, 2])) if args.table else None
    try:
        t0 = time.perf_counter()
        grasps = plan(mesh, n_candidates=args.candidates, seed=args.seed, top_k=args.top_k,
                      support_plane=plane)
        t_plan = time.perf_counter() - t0
    except ValueError as exc:
        parser.error(str(exc))
    print(f"planned {len(grasps)} grasp(s) in {t_plan:.1f} s")
    held = 0
    for rank, grasp in enumerate(grasps):
        t0 = time.perf_counter()
        try:
            result = lift_test(mesh, grasp, seed=args.seed, lift=args.lift,
                               shake=not args.no_shake, friction=args.friction,
                               density=args.density, support_plane=plane,
                               approach=args.approach)
        except ValueError as exc:
            parser.error(str(exc))
        wall = time.perf_counter() - t0
        held += result.success
        print(
            f"#{rank}: planner {grasp.reason} (eps {grasp.epsilon:.3f}); "
            f"{'HELD' if result.success else 'DROPPED'}: {result.reason}; "
            f"displacement {1000 * result.displacement:.1f} mm, slip {1000 * result.slip:.1f} mm, "
            f"held {result.held_s:.2f}/{result.total_s:.2f} s, mass {result.mass:.3f} kg, "
            f"fingers {'/'.join(result.finger_stops)}, {wall:.2f} s wall"
        )
    print(f"held {held}/{len(grasps)}")
    return 0 if held else 1
