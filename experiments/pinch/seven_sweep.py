import sys, numpy as np
exec(open(__file__.rsplit('/', 1)[0] + '/seven.py').read().split("ids = ")[0])
from grasp.candidates import _footprint_axes, _palm_pose
from grasp.screen import open_hand_lowest
from grasp.pinch import TIP_CLEARANCE_M
from grasp.autograsp import autograsp
from grasp.collision import CollisionScene
ids = benchmark_objects(100, 0)
table = SupportPlane(TABLE[:3], float(TABLE[3]))
do_lift = "--lift" in sys.argv
for oid in [a for a in sys.argv[1:] if not a.startswith("--")] or SEVEN:
    mesh, _ = resting_object(oid, ids.index(oid), 0)
    scene = CollisionScene(mesh, support_plane=table)
    axes = _footprint_axes(mesh, table)[::-1]
    out = []
    for cname, center in (("bbox", mesh.bounds.mean(0)), ("com", mesh.center_mass if mesh.is_watertight else mesh.bounds.mean(0))):
        for ai, a in enumerate(axes):
            for spread in (0, 30, 60, 90, 120):
                pose = _palm_pose(-table.normal, a, center, 0.3)
                travel = open_hand_lowest(table, pose[None], np.array([float(spread)]))[0] - TIP_CLEARANCE_M
                r = autograsp(scene, pose, spread_deg=spread, max_travel=travel, pinch=True)
                s = f"{cname}/{'narrow' if ai==0 else 'long'}/{spread}:{'FC' if r.success else '-'}"
                if r.success and do_lift:
                    L = lift_test(mesh, r, seed=0, support_plane=table, approach="guarded")
                    s += "H" if L.success else "D"
                out.append(s)
    print(oid, " ".join(out), flush=True)
