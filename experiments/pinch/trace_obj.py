import sys, numpy as np
exec(open(__file__.rsplit('/', 1)[0] + '/seven.py').read().split("ids = ")[0])
from grasp.candidates import _footprint_axes, _palm_pose
from grasp.screen import open_hand_lowest
from grasp.pinch import TIP_CLEARANCE_M
from grasp.autograsp import autograsp
from grasp.physics import world as W
ids = benchmark_objects(100, 0)
table = SupportPlane(TABLE[:3], float(TABLE[3]))
oid, axis, spread = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
mesh, _ = resting_object(oid, ids.index(oid), 0)
a = _footprint_axes(mesh, table)[::-1][axis]
pose = _palm_pose(-table.normal, a, mesh.bounds.mean(0), 0.3)
travel = open_hand_lowest(table, pose[None], np.array([spread]))[0] - TIP_CLEARANCE_M
r = autograsp(mesh, pose, spread_deg=spread, max_travel=travel, pinch=True, support_plane=table)
print("plan", r.success, r.reason, r.finger_stops, np.round(r.dofs_deg,1))
log=[]
orig=W.DynamicWorld.step
def step(self):
    orig(self)
    p,_=self.client.getBasePositionAndOrientation(self.object_id)
    log.append((np.array(p), self.finger_dofs_deg(), self.n_contacts()))
W.DynamicWorld.step=step
L = lift_test(mesh, r, seed=0, support_plane=table, approach="guarded", shake=False)
print("lift", L.success, L.reason, L.finger_stops, "mass", L.mass)
p0=log[0][0]
for i in range(0, len(log), 25):
    p,d,n=log[i]
    print(i, np.round(1000*(p-p0),1), np.round(d,0), n)
