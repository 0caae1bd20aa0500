import sys, time, numpy as np
from completion import grid as G
import completion.scenes as S
import igl
orig = G.voxelize_mesh
log = []
def full(v, f, t):
    idx = np.indices(G.GRID_SHAPE).reshape(3, -1).T
    w = np.abs(igl.fast_winding_number(np.asarray(v, float), np.asarray(f, np.int64), G.indices_to_points(idx, t))) > G.WINDING_THRESHOLD
    return w.reshape(G.GRID_SHAPE)
def both(v, f, t):
    a = orig(v, f, t)
    t0 = time.perf_counter(); b = full(v, f, t); dt = time.perf_counter() - t0
    b2 = b | (a & ~b)  # thin parts kept by the shell rule are in a
    log.append((int(a.sum()), int((b & ~a).sum()), dt))
    return a
G.voxelize_mesh = both
cond = sys.argv[1]; split = sys.argv[2]
for i in range(int(sys.argv[3])):
    log.clear()
    S.make_sequence(cond, split, i, seed=0)
    bad = [(a, m) for a, m, _ in log if m > 0.05 * max(a, 1)]
    print(i, "views", len(log), "missing>5%:", len(bad), bad[:4], "full ms %.0f" % (1000 * np.median([d for *_, d in log])), flush=True)
