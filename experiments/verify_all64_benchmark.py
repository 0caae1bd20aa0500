"""Scratch diagnostic (not a setting choice): the benchmark's true-mesh row planned with every
candidate autograsped and verify=8, executed by the benchmark's referee."""
import sys, dataclasses, numpy as np
from multiprocessing import Pool
from grasp.evaluate import benchmark as b
from grasp.evaluate.records import key_seed
from grasp.evaluate.config import BENCHMARK_TABLE

def one(job):
    index, oid = job
    from grasp.planner import plan
    from grasp.physics import lift_test
    from grasp.table import SupportPlane
    from completion.bullet import quiet_fds
    mesh, _ = b.resting_object(oid, index, 0)
    table = SupportPlane([0, 0, 1], 0.0)
    seed = key_seed(0, BENCHMARK_TABLE, index)
    out = {}
    for name, kw in (("b16_v4", dict(verify=4)), ("all_v8", dict(budget=None, verify=8))):
        g = plan(mesh, n_candidates=64, seed=seed, top_k=1, support_plane=table, **kw)
        if not g or not g[0].success:
            out[name] = False; continue
        with quiet_fds(1):
            out[name] = bool(lift_test(mesh, g[0], seed=seed, support_plane=table, approach="guarded").success)
    return oid, out

if __name__ == "__main__":
    ids = b.benchmark_objects(100, 0)
    with Pool(2) as p:
        res = p.map(one, list(enumerate(ids)))
    for k in ("b16_v4", "all_v8"):
        print(k, sum(r[k] for _, r in res), "/", len(res))
    print("gained with all_v8:", [o for o, r in res if r["all_v8"] and not r["b16_v4"]])
    print("lost with all_v8:", [o for o, r in res if r["b16_v4"] and not r["all_v8"]])
