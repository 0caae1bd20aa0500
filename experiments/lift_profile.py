"""Where a lift test's time goes: the benchmark's first N true meshes (top grasp, guarded, on the
table) and MVP completions; per phase steps and seconds, and world setup, V-HACD (cold)."""
import time, sys, tempfile, collections, pickle
import numpy as np
import grasp.physics.world as W
import grasp.physics.lift as L
from grasp.evaluate.benchmark import benchmark_objects, resting_object
from grasp.planner import plan
from grasp.physics import lift_test, convex_decomposition
from grasp.table import SupportPlane
T = SupportPlane([0, 0, 1], 0.0)
stats = collections.defaultdict(lambda: [0, 0.0])
phase = ["approach"]
step0 = W.DynamicWorld.step
def step(self):
    t = time.perf_counter(); step0(self); s = stats[phase[0]]; s[0] += 1; s[1] += time.perf_counter() - t
W.DynamicWorld.step = step
drive0 = W.DynamicWorld.drive_fingers
def drive(self, f):
    if phase[0] == "approach": phase[0] = "close"
    drive0(self, f)
W.DynamicWorld.drive_fingers = drive
sched0 = L._schedule
def sched(*a):
    out = sched0(*a)
    wrapped = []
    for name, n, f in out:
        def g(t, f=f, name=name):
            phase[0] = name; return f(t)
        wrapped.append((name, n, g))
    return wrapped
L._schedule = sched
init0 = W.DynamicWorld.__init__
def init(self, *a, **k):
    t = time.perf_counter(); init0(self, *a, **k); s = stats["world setup"]; s[0] += 1; s[1] += time.perf_counter() - t
W.DynamicWorld.__init__ = init
n = int(sys.argv[1])
ids = benchmark_objects(n, 0)
tests, walls, vh = 0, [], []
for i, oid in enumerate(ids):
    mesh, _ = resting_object(oid, i, 0)
    g = plan(mesh, seed=0, top_k=1, support_plane=T)[0]
    if not g.success: continue
    with tempfile.TemporaryDirectory() as d:
        t = time.perf_counter(); convex_decomposition(mesh, cache_dir=d); vh.append(time.perf_counter() - t)
        lift_test(mesh, g, seed=0, support_plane=T, approach="guarded", cache_dir=d)  # warm
        for k in stats: stats[k] = [0, 0.0]
        phase[0] = "approach"
        t = time.perf_counter(); lift_test(mesh, g, seed=0, support_plane=T, approach="guarded", cache_dir=d); walls.append(time.perf_counter() - t)
    tests += 1
    if tests == 1: acc = collections.defaultdict(lambda: [0, 0.0])
    for k, (c, s) in stats.items(): acc[k][0] += c; acc[k][1] += s
print(f"{tests} lift tests (true meshes, top grasp, guarded, on the table): median {np.median(walls)*1000:.0f} ms, mean {np.mean(walls)*1000:.0f} ms wall")
tot = sum(s for c, s in acc.values())
for k, (c, s) in acc.items():
    print(f"  {k:12s} {c/tests:7.1f} steps  {s/tests*1000:6.1f} ms  ({100*s/tot:.0f} % of the counted time)" + (f", {s/max(c,1)*1e6:.0f} µs a step" if k != 'world setup' else ''))
print(f"V-HACD of the true mesh (cold): median {np.median(vh)*1000:.0f} ms, max {max(vh)*1000:.0f} ms")
try:
    comps = pickle.load(open('/tmp/exp/completions.pkl', 'rb'))
    vv = []
    for oid, mesh, cam, truth in comps:
        with tempfile.TemporaryDirectory() as d:
            t = time.perf_counter(); convex_decomposition(mesh, cache_dir=d); vv.append(time.perf_counter() - t)
    print(f"V-HACD of {len(vv)} MVP completions (4 views, cold): median {np.median(vv)*1000:.0f} ms, max {max(vv)*1000:.0f} ms")
except FileNotFoundError:
    pass
