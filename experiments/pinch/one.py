import sys, numpy as np
exec(open(__file__.rsplit('/', 1)[0] + '/seven.py').read().split("ids = ")[0])
from grasp.candidates import _footprint_axes, _palm_pose
from grasp.screen import open_hand_lowest
from grasp.pinch import TIP_CLEARANCE_M
from grasp.autograsp import autograsp
ids = benchmark_objects(100, 0)
table = SupportPlane(TABLE[:3], float(TABLE[3]))
oid, where, axis, spread = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
mesh, _ = resting_object(oid, ids.index(oid), 0)
center = mesh.bounds.mean(0) if where == "bbox" else mesh.center_mass
a = _footprint_axes(mesh, table)[::-1][axis]
pose = _palm_pose(-table.normal, a, center, 0.3)
travel = open_hand_lowest(table, pose[None], np.array([spread]))[0] - TIP_CLEARANCE_M
r = autograsp(mesh, pose, spread_deg=spread, max_travel=travel, pinch=True, support_plane=table)
print("plan", r.success, r.reason, r.finger_stops, np.round(r.joints_deg,1), "rise", round(1000*r.wrist_rise.end_m,1), "mass", mesh.volume*500)
for c in r.contacts: print("  ", c.link, np.round(1000*c.point,1), np.round(c.normal,2))
for shake in (False, True):
    L = lift_test(mesh, r, seed=0, support_plane=table, approach="guarded", shake=shake)
    print("lift", shake, L.success, L.reason, L.finger_stops, np.round(L.joints_deg,1), "contacts", L.contacts, "slip", round(1000*L.slip,1))
