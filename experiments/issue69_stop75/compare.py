"""Stream val sequences through CompletionStream: MVP+fusion vs posed(+fusion or not)."""
import sys, glob, numpy as np, torch
from completion import load_model
from completion.model import load_checkpoint
from completion.data import load_sequence
from completion.stream import CompletionStream
from completion import evidence as E
from completion import grid as G
torch.set_num_threads(2)
mvp = load_model("mvp"); posed = load_checkpoint(sys.argv[1])
folder = sys.argv[2] if len(sys.argv) > 2 else "data/posed/val"
conds = sys.argv[3].split(",") if len(sys.argv) > 3 else ["tabletop", "camera_pan"]
orig_fuse = E.RegisteredEvidence.fuse
def run(seq, model, posed_model, fuse):
    E.RegisteredEvidence.fuse = orig_fuse if fuse else (lambda self, logits, *a, **k: logits)
    s = CompletionStream(model, registered=True, posed_model=posed_model)
    out = []
    for inp, g, pose, tg in zip(seq.inputs, seq.grid_to_camera, seq.camera_to_world, seq.targets):
        s.add_view(grid=G.VoxelGrid(inp, g), camera_to_world=pose)
        out.append(float(G.jaccard(s.logits >= 0, tg)))
    return np.array(out)
for c in conds:
    paths = sorted(glob.glob(f"{folder}/{c}_*.npz"))[:int(sys.argv[4]) if len(sys.argv) > 4 else 24]
    res = {k: [] for k in ("mvp_fused", "posed_fused", "posed_raw", "mvp_raw")}
    for p in paths:
        seq = load_sequence(p)
        res["mvp_fused"].append(run(seq, mvp, None, True))
        res["mvp_raw"].append(run(seq, mvp, None, False))
        res["posed_fused"].append(run(seq, mvp, posed, True))
        res["posed_raw"].append(run(seq, mvp, posed, False))
    for k, v in res.items():
        v = np.array(v)
        print(f"{c:12s} {k:12s} mean {v.mean():.3f} final {v[:, -1].mean():.3f} rise {(v[:, -3:].mean() - v[:, :3].mean()):+.3f} min-drop {np.diff(v, axis=1).min():+.3f}")
    sys.stdout.flush()
E.RegisteredEvidence.fuse = orig_fuse
