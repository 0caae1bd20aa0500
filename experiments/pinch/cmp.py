import json, sys
a=json.load(open(sys.argv[1]))['grasp_benchmark_objects']
b=json.load(open(sys.argv[2]))['grasp_benchmark_objects']
rows=sys.argv[3].split(',') if len(sys.argv)>3 else ['true_mesh','mvp_1view','mvp_4views']
tot={r:[0,0] for r in rows}
for ra, rb in zip(a,b):
    assert ra['id']==rb['id']
    for row in rows:
        x, y = ra['rows'].get(row), rb['rows'].get(row)
        if x is None or y is None: continue
        tot[row][0]+=x['held']; tot[row][1]+=y['held']
        if x['held'] != y['held']:
            print(f"{rb['id']:24s} {row:20s} {x['held']!s:5} -> {y['held']!s:5} {x.get('kind','-'):22s} -> {y.get('kind','-'):22s} h={100*rb['size_m'][2]:.1f}cm  {y['reason'][:70]}")
print(tot)
