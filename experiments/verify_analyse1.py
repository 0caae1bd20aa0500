import json, sys, itertools
recs = [json.loads(l) for l in open(sys.argv[1])]
print(len(recs), 'objects')
for row in ("true_mesh", "mvp_4views"):
    print('==', row)
    base = 0
    for o in recs:
        rs = o["rows"].get(row, [])
        if o.get(row + "_top_success") and rs and rs[0]["rank"] == 0 and rs[0]["success"]:
            base += rs[0]["referee"]
    anyhold = sum(any(r["referee"] for r in o["rows"].get(row, [])) for o in recs)
    print(f'unverified top-1 held {base}; some of first 5 eligible holds {anyhold}')
    for K in (1, 2, 3):
        for N in (1, 2, 3, 4, 5):
            held = 0; tried_tot = 0; agree = 0; n_ag = 0
            for o in recs:
                rs = o["rows"].get(row, [])
                pick = None; tried = 0
                for r in rs[:N]:
                    tried += 1
                    if all(r["trials"][:K]):
                        pick = r; break
                if pick is None:
                    # untried successes come next
                    rest = [r for r in rs[N:] if r["success"]]
                    if rest: pick = rest[0]
                    else:
                        dropped = [r for r in rs[:N] if r["success"]]
                        dropped.sort(key=lambda r: -sum(r["trials"][:K]))
                        pick = dropped[0] if dropped else None
                        if pick is None and not o.get(row + "_top_success"): pick = None
                tried_tot += tried
                if pick is not None: held += pick["referee"]
                for r in rs[:N]:
                    n_ag += 1; agree += (all(r["trials"][:K]) == r["referee"])
            print(f'K={K} N={N}: held {held}/{len(recs)}, mean grasps tried {tried_tot/len(recs):.2f}, trial-vs-referee agreement {agree}/{n_ag}')
