import math, numpy as np, sys
sys.argv=[sys.argv[0]]
exec(open('/tmp/pinch_try.py').read().split("for yaw in (0.0")[0])
from grasp.physics import lift_test
for yaw in (0.0, math.pi/2):
  for spread in (0.0, 60.0):
    pose, travel = pinch_start([0,0], yaw, spread)
    r = autograsp(box, pose, spread_deg=spread, max_travel=travel, support_plane=FLOOR, pinch=True)
    L = lift_test(box, r, support_plane=FLOOR, approach="guarded")
    d = np.abs(np.asarray(L.joints_deg) - np.asarray(r.joints_deg))
    print(f"yaw {math.degrees(yaw):.0f} spread {spread:.0f} FC {r.success} held {L.success} maxdiff {d.max():.1f} planned {np.round(r.joints_deg,1)} exec {np.round(L.joints_deg,1)}")
