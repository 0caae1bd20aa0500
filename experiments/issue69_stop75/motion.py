"""Tabletop test sequences 0-9 (the evaluation's): per camera motion, mean / final / rise of the
uncut Jaccard, for MVP, MVP + fusion (stop 68) and mvp_posed + fusion (shipped)."""
import numpy as np, torch
from completion import load_model
from completion.scenes import make_sequence
from completion.stream import CompletionStream
from completion import grid as G
torch.set_num_threads(2)
mvp, posed = load_model("mvp"), load_model("mvp_posed")
rows = {"MVP": dict(registered=False), "MVP + fusion (stop 68)": dict(), "posed + fusion (shipped)": dict(posed_model=posed)}
res = {k: {} for k in rows}
for i in range(10):
    seq = make_sequence("tabletop", "test", i, seed=0)
    m = seq.meta["camera_motion"]
    for k, kw in rows.items():
        s = CompletionStream(mvp, **kw); out = []
        for inp, g, pose, tg in zip(seq.inputs, seq.grid_to_camera, seq.camera_to_world, seq.targets):
            s.add_view(grid=G.VoxelGrid(inp, g), camera_to_world=pose)
            out.append(float(G.jaccard(s.logits >= 0, tg)))
        res[k].setdefault(m, []).append(out)
for m in ("still", "pan", "arc"):
    for k in rows:
        v = np.array(res[k].get(m, []))
        if len(v):
            print(f"{m:5s} ({len(v)}) {k:26s} mean {v.mean():.3f} final {v[:, -1].mean():.3f} rise {v[:, -3:].mean() - v[:, :3].mean():+.3f} worst step {np.diff(v, axis=1).min():+.3f}")
