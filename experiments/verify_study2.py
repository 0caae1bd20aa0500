"""Study 2 (training split): every candidate autograsped; per candidate its screen position, the
pinch-first screen position, rank key; the first 5 eligible grasps of each search variant
(all 64, the screen's 16, a screen keeping the pinches) lift-tested by the referee (true object)
and by 2 verification trials on the planned mesh."""
import json, sys, zlib, dataclasses, time, math
import numpy as np
from multiprocessing import Pool

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
    from grasp.planner import rank, rank_key, screen_order, distinct
    from grasp.candidates import table_candidates, STANDOFF_M
    from grasp.collision import CollisionScene
    from grasp.autograsp import autograsp
    from grasp.physics import lift_test
    from grasp.table import SupportPlane, crosses
    from grasp import verify as V
    from completion.bullet import quiet_fds
    seed = 1000 + index
    scene = b.make_scene(object_id, index, 7, _state["renderer"])
    table = SupportPlane([0, 0, 1], 0.0)
    out = {"id": object_id, "rows": {}}
    trials = V.trials(seed)
    for row in ("true_mesh", "mvp_4views"):
        if row == "true_mesh":
            mesh, camera = scene.mesh, np.eye(4)
        else:
            mesh, camera = b.completion_mesh(scene, "mvp", 4, _state["models"])
        if mesh is None:
            out["rows"][row] = None; continue
        plane = table.transformed(camera)
        sc = CollisionScene(mesh).with_support_plane(plane)
        travel = float(np.linalg.norm(mesh.extents)) + 2 * STANDOFF_M
        cands = table_candidates(mesh, plane, travel=travel, n_candidates=64, seed=seed)
        order = screen_order(sc, cands, travel)
        pos = {i: k for k, i in enumerate(order)}
        grs = []
        for i, c in enumerate(cands):
            r = autograsp(sc, c.palm_pose, spread_deg=c.spread_deg,
                          max_travel=travel if c.travel is None else c.travel, quality=False)
            if crosses(plane, r): continue
            grs.append((i, rank([r], sc)[0]))
        grs.sort(key=lambda t: (*rank_key(t[1]), -t[0]), reverse=True)
        variants = {"all": set(range(len(cands))), "screen16": set(order[:16]),
                    "pinch16": set(sorted(order, key=lambda i: (cands[i].source != "pinch", pos[i]))[:16])}
        test = set()
        for name, allowed in variants.items():
            dd = distinct([g for i, g in grs if i in allowed])
            ids = {id(g): i for i, g in grs}
            el = [ids[id(g)] for g in dd if V.eligible(g)][:5]
            test |= set(el)
        recs = []
        for i, g in grs:
            rec = {"i": i, "source": cands[i].source, "pos": pos[i], "success": bool(g.success),
                   "eligible": bool(V.eligible(g)), "p": None if math.isnan(g.hold_probability) else round(g.hold_probability, 3),
                   "palm": bool(any(c.link == "palm" for c in g.contacts)),
                   "pose": np.round(g.palm_pose, 5).tolist()}
            if i in test:
                world = dataclasses.replace(g, palm_pose=camera @ g.palm_pose)
                with quiet_fds(1):
                    ref = lift_test(scene.mesh, world, seed=seed + 77, support_plane=table, approach="guarded")
                rec["referee"] = bool(ref.success)
                rec["trials"] = [V.run_trial(mesh, g, plane, t).held for t in trials]
            recs.append(rec)
        out["rows"][row] = recs
    return out

if __name__ == "__main__":
    from completion.objects import object_ids
    start, n, outp = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
    pool = object_ids("train")
    order = np.random.default_rng([7, zlib.crc32(b"verify-study")]).permutation(len(pool))
    jobs = [(i, pool[k]) for i, k in enumerate(order[:n])][start:]
    t0 = time.time()
    with Pool(2, initializer=init) as p, open(outp, "a") as f:
        for k, rec in enumerate(p.imap(one, jobs), 1):
            f.write(json.dumps(rec) + "\n"); f.flush()
            print(k, f"{time.time()-t0:.0f}s", flush=True)
