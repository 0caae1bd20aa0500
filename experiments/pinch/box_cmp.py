import numpy as np, trimesh
from grasp.planner import plan
from grasp.physics import lift_test
from grasp.table import SupportPlane
FLOOR = SupportPlane(np.array([0,0,1.0]), 0.0)
for dims in ([0.06,0.06,0.12],[0.08,0.05,0.05],[0.12,0.08,0.01],[0.10,0.03,0.015]):
    box = trimesh.creation.box(dims); box.apply_translation([0,0,dims[2]/2])
    g = plan(box, support_plane=FLOOR, top_k=1)[0]
    L = lift_test(box, g, support_plane=FLOOR, approach="guarded")
    d = np.abs(np.asarray(L.joints_deg)-np.asarray(g.joints_deg))
    rise = None if g.wrist_rise is None else g.wrist_rise.end_m
    print(dims, g.kind, g.success, "held", L.success, "max diff", round(d.max(),1), "mean", round(d.mean(),1), np.round(g.joints_deg,1), np.round(L.joints_deg,1))
