import sys, numpy as np
exec(open(__file__.rsplit('/', 1)[0] + '/mass.py').read().split("for oid in")[0])
from grasp.planner import plan
from grasp.verify import describe
for oid in sys.argv[1:]:
    mesh, _ = resting_object(oid, ids.index(oid), 0)
    g = plan(mesh, n_candidates=64, seed=0, top_k=8, support_plane=table, verify=4)
    for x in g:
        print(oid, x.kind, x.success, round(x.hold_probability or -1, 2), round(x.epsilon, 3), describe(x.verification), x.reason[:60])
