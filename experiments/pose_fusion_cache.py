import sys, time, numpy as np, pickle
from completion.scenes import make_sequence
from completion.depth_camera import Renderer
SPLIT = sys.argv[4] if len(sys.argv) > 4 else "test"
cond = sys.argv[1]; n = int(sys.argv[2]); start = int(sys.argv[3]) if len(sys.argv) > 3 else 0
r = Renderer()
for i in range(start, start+n):
    t=time.time()
    s = make_sequence(cond, SPLIT, i, 0, keep_depth=True, renderer=r)
    pickle.dump(s, open(f"/tmp/exp/{SPLIT}_{cond}_{i}.pkl","wb"))
    print(cond, i, s.meta.get("camera_motion"), s.depth.shape, round(time.time()-t,1), flush=True)
