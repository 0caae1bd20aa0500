import pickle, sys, numpy as np, glob
from completion.model import load_model
from completion.stream import CompletionStream
from completion import grid as G
from grasp_client.wire import SupportPlane
M = load_model('completion/weights/mvp.pt')
def jac(a,b): u=(a|b).sum(); return (a&b).sum()/u if u else 1.0
split = sys.argv[1]
for f in sorted(glob.glob(f'/tmp/exp/{split}_tabletop_*.pkl'), key=lambda x: int(x.split('_')[-1][:-4])):
    s = pickle.load(open(f,'rb')); K = G.Intrinsics(**s.meta['intrinsics'])
    st = CompletionStream(M); js=[]
    for t in range(12):
        st.add_view(depth=s.depth[t], intrinsics=K, mask=(s.mask[t]==0), camera_to_world=s.camera_to_world[t], support_plane=SupportPlane.from_values(s.meta['support_plane']))
        js.append(jac(st.completion().occupancy, s.targets[t]))
    d = np.diff(js)
    print(f.split('/')[-1], s.meta['camera_motion'], 'maxdrop %.3f' % -d.min(), 'first %.3f last %.3f mean %.3f' % (js[0], js[-1], np.mean(js)), flush=True)
