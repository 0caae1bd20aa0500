import json, sys
recs = [json.loads(l) for l in open(sys.argv[1])]
print(len(recs), 'objects')
def distinct_ok(g, kept):
    import numpy as np
    for o in kept:
        a, b = np.array(g["pose"]), np.array(o["pose"])
        near = np.linalg.norm(a[:3,3]-b[:3,3]) < 0.01
        cos = (np.trace(a[:3,:3].T @ b[:3,:3]) - 1)/2
        if near and cos > np.cos(np.radians(10)): return False
    return True
def ranked(rs, allowed):
    kept = []
    for g in rs:
        if g["i"] in allowed and distinct_ok(g, kept): kept.append(g)
    return kept
for row in ("true_mesh", "mvp_4views"):
    print("==", row)
    for variant in ("screen16", "pinch16", "all"):
        res = {}
        unknown = 0
        best_in = 0; best_lift_in = 0; nb = 0
        for o in recs:
            rs = o["rows"].get(row)
            if not rs: continue
            n = max(g["i"] for g in rs) + 1
            order = sorted(rs, key=lambda g: g["pos"])
            if variant == "all": allowed = {g["i"] for g in rs}
            elif variant == "screen16": allowed = {g["i"] for g in rs if g["pos"] < 16}
            else:
                allowed = {g["i"] for g in sorted(rs, key=lambda g: (g["source"] != "pinch", g["pos"]))[:16]}
            kk = ranked(rs, allowed)
            for N in (0, 1, 2, 4, 8):
                pick = None; tried = 0
                el = [g for g in kk if g["eligible"]]
                if N == 0:
                    pick = kk[0] if kk and kk[0]["success"] else None
                else:
                    for g in el[:N]:
                        if "trials" not in g: unknown += 1; break
                        tried += 1
                        if all(g["trials"]): pick = g; break
                    if pick is None:
                        t = el[:N]
                        rest = [g for g in kk if g["success"] and g not in t]
                        if rest: pick = rest[0]
                        else:
                            d = [g for g in t if g["success"]]
                            d.sort(key=lambda g: -sum(g.get("trials", [0])))
                            pick = d[0] if d else None
                if pick is not None and "referee" not in pick: unknown += 1
                res.setdefault(N, 0)
                res[N] += bool(pick and pick.get("referee"))
        print(variant, {f"N={k}": v for k, v in res.items()}, "unknown", unknown)
    # ceiling: any eligible tested grasp held by referee
    ceil = sum(any(g.get("referee") for g in (o["rows"].get(row) or [])) for o in recs)
    print("some tested grasp holds (ceiling of what was tested):", ceil)
    # screen recall: best of all 64 by ranking in screen16
    top_in = 0; lift_in = 0; nl = 0; n = 0
    for o in recs:
        rs = o["rows"].get(row)
        if not rs: continue
        kk = ranked(rs, {g["i"] for g in rs})
        if kk and kk[0]["success"]:
            n += 1; top_in += kk[0]["pos"] < 16
        held = [g for g in kk if g.get("referee")]
        if held:
            nl += 1; lift_in += held[0]["pos"] < 16
    print(f"best of all 64 by the ranking in the screen's 16: {top_in}/{n}; best holding (by the lift, first in ranking) in the screen's 16: {lift_in}/{nl}")
