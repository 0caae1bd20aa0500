"""The seven flat/small benchmark objects: plan on the true mesh with the table, lift-test the top grasp."""
import sys, time, json, numpy as np
from grasp.evaluate.benchmark import benchmark_objects, resting_object, grasp_kind, TABLE
from grasp.planner import plan
from grasp.physics import lift_test
from grasp.table import SupportPlane
SEVEN = ["proc/hammer/9", "proc/hammer/219", "proc/hammer/809", "named/toy_concave_box",
         "proc/t_shape/639", "proc/cone/619", "urdf/990"]
ids = benchmark_objects(100, 0)
table = SupportPlane(TABLE[:3], float(TABLE[3]))
which = sys.argv[1:] or SEVEN
for oid in which:
    i = ids.index(oid)
    mesh, _ = resting_object(oid, i, 0)
    t = time.perf_counter()
    g = plan(mesh, n_candidates=64, seed=0, top_k=3, support_plane=table)
    dt = time.perf_counter() - t
    best = g[0]
    line = f"{oid:24s} {np.round(100*mesh.extents,1)} cm  plan {dt:.2f}s  top: {best.success} {best.kind} {best.reason[:70]}"
    if best.success:
        L = lift_test(mesh, best, seed=0, support_plane=table, approach="guarded")
        line += f" | lift {L.success} {L.reason[:50]} kind={grasp_kind(best)}"
    print(line, flush=True)
