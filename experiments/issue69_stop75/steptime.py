import time, sys, numpy as np, torch
torch.set_num_threads(2)
from completion.model import load_model
from completion.scenes import make_sequence
from completion.stream import CompletionStream
from completion import grid as G
mvp=load_model("mvp"); posed=load_model("mvp_posed")
seq=make_sequence("tabletop","test",4,keep_depth=True); k=G.Intrinsics(**seq.meta["intrinsics"])
for name, target, pm in (("mvp", mvp, None), ("posed", posed, posed), ("mvp", mvp, None), ("posed", posed, posed)):
    orig=target.step; times=[]
    def timed(*a, _o=orig, **kw):
        t0=time.perf_counter(); r=_o(*a, **kw); times.append(time.perf_counter()-t0); return r
    target.step=timed
    tot=[]
    for rep in range(2):
        s=CompletionStream(mvp, posed_model=pm)
        for t in range(12):
            t0=time.perf_counter()
            s.add_view(depth=seq.depth[t], intrinsics=k, mask=seq.mask[t]==0, camera_to_world=seq.camera_to_world[t]); tot.append(time.perf_counter()-t0)
    target.step=orig
    print(name, "step median %.1f ms, add_view median %.1f ms" % (1000*np.median(times), 1000*np.median(tot)))
