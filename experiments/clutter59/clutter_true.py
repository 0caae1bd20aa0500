"""True-mesh clutter row on N scenes: plan with the neighbours as obstacles (and ignoring them), lift with neighbours."""
import sys, time, numpy as np
from grasp.evaluate.clutter import scene_objects, disturbed
from grasp.evaluate.benchmark import TABLE
from grasp.obstacles import Obstacles
from grasp.planner import plan
from grasp.physics import lift_test
from grasp.table import SupportPlane
table = SupportPlane(TABLE[:3], float(TABLE[3]))
n0, n1 = int(sys.argv[1]), int(sys.argv[2])
tot = {"obst": 0, "ign": 0}
for i in range(n0, n1):
    t = time.perf_counter()
    tid, target, names, nbs, gaps, _ = scene_objects(i, 0)
    line = f"{i:3d} {tid:22s} {len(nbs)} nb gaps {np.round(100*np.array(gaps)).astype(int).tolist()} |"
    for name, obs in (("obst", Obstacles.from_meshes(nbs)), ("ign", None)):
        g = plan(target, n_candidates=64, seed=0, top_k=1, support_plane=table, obstacles=obs)[0]
        if not g.success:
            line += f" {name}: NO GRASP ({g.reason[:70]})"
            continue
        L = lift_test(target, g, seed=0, support_plane=table, approach="guarded", neighbours=nbs)
        d = disturbed(L)
        ok = L.success and d is None
        tot[name] += ok
        line += f" {name}: {'OK' if ok else 'FAIL'} held={L.success} {d or ''} moved {100*L.neighbour_moved:.1f}"
    print(line, f"{time.perf_counter()-t:.1f}s", flush=True)
print(tot)
