"""Verification study on training-split objects: per object and row (true mesh, MVP 4 views), the
first M eligible grasps of the ranking (budget 16), each lift-tested by the referee (true object,
benchmark settings, its own seed) and by K verification trials on the planned mesh."""
import json, sys, zlib, dataclasses, time
import numpy as np
from multiprocessing import Pool

M, K = 5, 3
_state = {}

def init():
    import completion
    from completion.render import Renderer
    from grasp.evaluate.rows import ModelRow
    model = completion.load_model("mvp")
    th = getattr(model, "threshold", None) or 0.5
    _state["models"] = {"mvp": ModelRow("mvp", model, float(th))}
    _state["renderer"] = Renderer()

def one(job):
    index, object_id = job
    from grasp.evaluate import benchmark as b
    from grasp.planner import plan, distinct, rank
    from grasp.physics import lift_test
    from grasp.table import SupportPlane
    from grasp import verify as V
    from completion.bullet import quiet_fds
    seed = 1000 + index
    scene = b.make_scene(object_id, index, 7, _state["renderer"])
    table = SupportPlane([0, 0, 1], 0.0)
    out = {"id": object_id, "rows": {}}
    for row in ("true_mesh", "mvp_4views"):
        if row == "true_mesh":
            mesh, camera = scene.mesh, np.eye(4)
        else:
            mesh, camera = b.completion_mesh(scene, "mvp", 4, _state["models"])
        if mesh is None:
            out["rows"][row] = []; continue
        plane = table.transformed(camera)
        ranked = plan(mesh, seed=seed, top_k=None, support_plane=plane)
        ranked = distinct(ranked)
        recs = []
        trials = V.trials(seed, V.VerifySettings(trials=K))
        for r, g in enumerate(ranked):
            if len(recs) >= M: break
            if not V.eligible(g): continue
            world = dataclasses.replace(g, palm_pose=camera @ g.palm_pose)
            with quiet_fds(1):
                ref = lift_test(scene.mesh, world, seed=seed + 77, support_plane=table, approach="guarded")
            ver = [V.run_trial(mesh, g, plane, t) for t in trials]
            recs.append({"rank": r, "success": bool(g.success), "p": None if np.isnan(g.hold_probability) else g.hold_probability,
                         "referee": bool(ref.success), "trials": [o.held for o in ver], "why": [o.reason[:60] for o in ver]})
        top = ranked[0] if ranked else None
        out["rows"][row] = recs
        out[row + "_top_success"] = bool(top is not None and top.success)
    return out

if __name__ == "__main__":
    from completion.objects import object_ids
    n, outp = int(sys.argv[1]), sys.argv[2]
    pool = object_ids("train")
    order = np.random.default_rng([7, zlib.crc32(b"verify-study")]).permutation(len(pool))
    jobs = [(i, pool[k]) for i, k in enumerate(order[:n])]
    t0 = time.time()
    with Pool(2, initializer=init) as p, open(outp, "w") as f:
        for k, rec in enumerate(p.imap(one, jobs), 1):
            f.write(json.dumps(rec) + "\n"); f.flush()
            print(k, f"{time.time()-t0:.0f}s", flush=True)
