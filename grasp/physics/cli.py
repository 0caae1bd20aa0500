"""``python -m grasp.physics MESH``: plan a grasp on a mesh, then lift-test it in pybullet."""

from __future__ import annotations

from completion.objects import mesh_from_spec
from grasp.physics.lift import lift_test
from grasp.physics.settings import APPROACHES, DENSITY_KG_M3
from grasp.quality import MU_RUBBER
from grasp_client.wire import SupportPlane


def main(argv: list[str] | None = None) -> int:
    import argparse
    import time

    from grasp.planner import plan

    parser = argparse.ArgumentParser(formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        prog="python -m grasp.physics",
        description="Plan a BarrettHand grasp on a mesh, then lift-test it in pybullet dynamics.",
    )
    parser.add_argument("mesh", help="mesh file (OBJ/STL/PLY, metres) or an object id")
    parser.add_argument("--seed", type=int, default=0, help="planner and shake seed")
    parser.add_argument("--candidates", type=int, default=64, help="planner candidates")
    parser.add_argument("--top-k", type=int, default=1, help="lift-test the best K grasps")
    parser.add_argument("--lift", type=float, default=0.10, help="lift height (m)")
    parser.add_argument("--no-shake", action="store_true", help="lift only")
    parser.add_argument("--friction", type=float, default=MU_RUBBER, help="hand–object μ")
    parser.add_argument("--density", type=float, default=DENSITY_KG_M3, help="kg/m³")
    parser.add_argument("--table", action="store_true",
                        help="the object stands on a table under its lowest point (z up): "
                        "planned with it and lift-tested on it")
    parser.add_argument(
        "--approach", choices=APPROACHES, default="planned",
        help="planned: to the planned pose (default); guarded: toward it, stopping at the first "
        "touch, as a robot executes a plan",
    )
    args = parser.parse_args(argv)
    try:
        mesh = mesh_from_spec(args.mesh)
        plane = SupportPlane([0.0, 0.0, 1.0], -float(mesh.bounds[0, 2])) if args.table else None
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
            result = lift_test(
                mesh,
                grasp,
                seed=args.seed,
                lift=args.lift,
                shake=not args.no_shake,
                friction=args.friction,
                density=args.density,
                support_plane=plane,
                approach=args.approach,
            )
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


if __name__ == "__main__":
    raise SystemExit(main())
