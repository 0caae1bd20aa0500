"""How much of the object's surface the views have seen, first view vs last, per camera motion."""
import numpy as np
from scipy import ndimage
from completion.scenes import make_sequence
from grasp.evaluate.rows import registered_fusion
out = {}
for cond in ("tabletop", "camera_pan"):
    for i in range(10):
        seq = make_sequence(cond, "test", i, seed=0)
        fused = registered_fusion(seq.inputs, seq.grid_to_camera, seq.camera_to_world)
        cov = []
        for t in (0, len(seq) - 1):
            tg = seq.targets[t]
            shell = tg & ~ndimage.binary_erosion(tg)
            near = ndimage.binary_dilation(fused[t], iterations=1)
            cov.append((shell & near).sum() / max(shell.sum(), 1))
        out.setdefault((cond, seq.meta.get("camera_motion", "pan")), []).append(cov)
for k, v in out.items():
    v = np.array(v)
    print(k, len(v), "surface seen: first view %.2f, all 12 views %.2f" % (v[:, 0].mean(), v[:, 1].mean()))
