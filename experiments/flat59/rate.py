"""Hold rate of the six flat objects' force-closure table pinches under the referee, across shake seeds and friction."""
import numpy as np
exec(open(__file__.rsplit('/', 1)[0] + '/mass.py').read().split("for oid in")[0])
for oid in ["proc/hammer/809", "proc/t_shape/639", "proc/cone/619", "urdf/990", "urdf/988"]:
    mesh, _ = resting_object(oid, ids.index(oid), 0)
    scene = CollisionScene(mesh, support_plane=table)
    axes = _footprint_axes(mesh, table)[::-1]
    for ai, a in enumerate(axes):
        for spread in (0, 60):
            pose = _palm_pose(-table.normal, a, mesh.bounds.mean(0), 0.3)
            travel = open_hand_lowest(table, pose[None], np.array([float(spread)]))[0] - TIP_CLEARANCE_M
            r = autograsp(scene, pose, spread_deg=spread, max_travel=travel, pinch=True)
            if not r.success:
                continue
            res = []
            for mu in (0.8, 1.0):
                for seed in range(6):
                    L = lift_test(mesh, r, seed=seed, support_plane=table, approach="guarded", friction=mu)
                    res.append((L.success, L.reason[:40]))
            held = sum(h for h, _ in res)
            why = {}
            for h, w in res:
                if not h:
                    why[w] = why.get(w, 0) + 1
            print(f"{oid:18s} {'nar' if ai == 0 else 'long'}/{spread}: held {held}/12  {why}", flush=True)
