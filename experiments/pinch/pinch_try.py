import math, time, numpy as np, trimesh
from grasp.autograsp import autograsp
from grasp.table import SupportPlane, hand_clearance
from grasp.screen import open_hand_lowest
from grasp.pinch import TIP_CLEARANCE_M
FLOOR = SupportPlane(np.array([0,0,1.0]), 0.0)
def pinch_start(center, yaw, spread, plane=FLOOR):
    pose = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    pose[:3,:3] = np.array([[c, -s, 0],[s, c, 0],[0,0,1]]) @ np.diag([1,-1,-1])  # z down
    pose[:3,3] = [center[0], center[1], 0.3]
    low = open_hand_lowest(plane, pose[None], np.array([spread]))[0]
    return pose, low - TIP_CLEARANCE_M
import sys
dims = [float(v) for v in sys.argv[1:4]] if len(sys.argv) > 3 else [0.12, 0.08, 0.01]
box = trimesh.creation.box(dims); box.apply_translation([0,0,dims[2]/2])
for yaw in (0.0, math.pi/2):
  for spread in (0.0, 60.0):
    pose, travel = pinch_start([0,0], yaw, spread)
    t=time.perf_counter()
    r = autograsp(box, pose, spread_deg=spread, max_travel=travel, support_plane=FLOOR, pinch=True)
    dt=time.perf_counter()-t
    print(f"yaw {math.degrees(yaw):.0f} spread {spread}: {r.success} {r.reason} eps {r.epsilon:.3f} stops {r.finger_stops} dofs {np.round(r.dofs_deg,1)} rise {1000*r.wrist_rise.end_m if r.wrist_rise else 0:.1f} mm  {1000*dt:.0f} ms contacts {[c.link for c in r.contacts]}")
from grasp.physics import lift_test
for yaw in (math.pi/2,):
    pose, travel = pinch_start([0,0], yaw, 0.0)
    r = autograsp(box, pose, spread_deg=0.0, max_travel=travel, support_plane=FLOOR, pinch=True)
    t=time.perf_counter()
    L = lift_test(box, r, support_plane=FLOOR, approach="guarded")
    print("lift:", L.success, L.reason, "executed", np.round(L.joints_deg,1), "planned", np.round(r.joints_deg,1), f"{time.perf_counter()-t:.2f}s")
