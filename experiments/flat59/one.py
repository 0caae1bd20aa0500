import sys, numpy as np
exec(open(__file__.rsplit('/', 1)[0] + '/mass.py').read().split("for oid in")[0])
oid = sys.argv[1]
mesh, _ = resting_object(oid, ids.index(oid), 0)
print("extents cm", np.round(100*mesh.extents, 2), "bounds z", mesh.bounds[:, 2])
scene = CollisionScene(mesh, support_plane=table)
axes = _footprint_axes(mesh, table)[::-1]
for ai, a in enumerate(axes):
    for spread in (0, 60):
        pose = _palm_pose(-table.normal, a, mesh.bounds.mean(0), 0.3)
        travel = open_hand_lowest(table, pose[None], np.array([float(spread)]))[0] - TIP_CLEARANCE_M
        r = autograsp(scene, pose, spread_deg=spread, max_travel=travel, pinch=True)
        print(ai, spread, r.success, r.reason, r.dofs_deg, r.finger_stops, r.approach_stop, round(r.travel,4), [c.link for c in r.contacts])
