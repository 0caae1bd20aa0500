import sys, numpy as np
from completion import grid as G
import completion.scenes as S
orig = G.voxelize_mesh
log = []
def spy(v, f, t):
    pts = G.sample_surface(np.asarray(v, float), np.asarray(f, np.int64), spacing=G.pitch_of(t) / 2)
    idx = G.points_to_indices(pts, t) if hasattr(G, "points_to_indices") else (np.linalg.inv(t)[:3, :3] @ pts.T + np.linalg.inv(t)[:3, 3:]).T
    out = np.any((idx < -0.5) | (idx > 39.5), axis=1).mean()
    log.append(out)
    return orig(v, f, t)
G.voxelize_mesh = spy
for cond in sys.argv[1].split(","):
    per = []
    for i in range(10):
        log.clear(); S.make_sequence(cond, "test", i, seed=0); per.append(list(log))
    per = np.array(per)
    print(cond, "surface outside the view's grid: mean %.3f, views with >5%%: %d of %d, max %.2f" % (per.mean(), (per > 0.05).sum(), per.size, per.max()), flush=True)
