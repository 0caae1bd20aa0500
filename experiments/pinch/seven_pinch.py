import sys, numpy as np
exec(open(__file__.rsplit('/', 1)[0] + '/seven.py').read().split("ids = ")[0])
from grasp.candidates import table_candidates
from grasp.autograsp import autograsp
from grasp.collision import CollisionScene
ids = benchmark_objects(100, 0)
table = SupportPlane(TABLE[:3], float(TABLE[3]))
for oid in (sys.argv[1:] or SEVEN):
    mesh, _ = resting_object(oid, ids.index(oid), 0)
    scene = CollisionScene(mesh, support_plane=table)
    cands = [c for c in table_candidates(mesh, table) if c.source == "table pinch"]
    print(oid, len(cands), "pinch candidates; height", round(100*mesh.bounds[1,2],1))
    for c in cands:
        r = autograsp(scene, c.palm_pose, spread_deg=c.spread_deg, max_travel=c.travel, pinch=True)
        print(f"   spread {c.spread_deg:3.0f} y {np.round(c.palm_pose[:3,1],2)} {r.success} {r.reason[:60]} stops {r.finger_stops} dofs {np.round(r.dofs_deg[1:],0)} eps {r.epsilon:.3f} contacts {sorted(set(x.link for x in r.contacts))}")
