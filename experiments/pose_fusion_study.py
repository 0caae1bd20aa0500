import glob, os, pickle, sys, numpy as np, torch
from scipy.ndimage import map_coordinates
from completion import grid as G
from completion.model import load_model
torch.set_num_threads(2)
CUT = os.environ.get('CUT') == '1'
M = load_model('/work/main/completion/weights/mvp.pt').eval()

def jac(a, b):
    u = (a | b).sum(); return 1.0 if u == 0 else (a & b).sum() / u

def logits(seq, memory=True):
    x = torch.from_numpy(seq.inputs[None].astype(np.float32))
    with torch.no_grad():
        if memory: return M(x)[0].numpy()
        return M(x[0][:, None])[:, 0].numpy()

def centres_world(seq, t):
    c = G.voxel_centers(seq.grid_to_camera[t]); return G.transform_points(c, seq.camera_to_world[t])

def sample(vol, seq, s, world, fill=np.nan):
    cam = G.transform_points(world, np.linalg.inv(seq.camera_to_world[s]))
    idx = G.transform_points(cam, np.linalg.inv(seq.grid_to_camera[s]))
    inside = np.all((idx >= -0.5) & (idx <= 39.5), axis=1)
    val = map_coordinates(np.pad(vol, 1, mode='edge'), (idx + 1).T, order=1, mode='nearest')
    return np.where(inside, val, fill)

def free_evidence(seq, s, world, margin_vox=1.5, silhouette=True):
    """1 where view s's depth proves the point empty, else 0"""
    K = seq.meta['intrinsics']; d = seq.depth[s]; m = seq.mask[s]
    cam = G.transform_points(world, np.linalg.inv(seq.camera_to_world[s]))
    z = cam[:, 2]; ok = z > 1e-3
    u = np.round(K['fx'] * cam[:, 0] / np.where(ok, z, 1) + K['cx']).astype(int)
    v = np.round(K['fy'] * cam[:, 1] / np.where(ok, z, 1) + K['cy']).astype(int)
    ok &= (u >= 0) & (u < K['width']) & (v >= 0) & (v < K['height'])
    out = np.zeros(len(world), bool)
    uu, vv = u[ok], v[ok]
    dd = d[vv, uu]; mm = m[vv, uu]
    pitch = G.pitch_of(seq.grid_to_camera[s])
    valid = dd > 0
    obj = mm >= 0
    free = valid & (z[ok] < dd - margin_vox * pitch) & (obj | silhouette)
    out[np.flatnonzero(ok)[free]] = True
    return out

def run(seq, mode, memory=False, free=False, clip=6.0, free_w=1.0, margin=1.5, sil=True):
    L = logits(seq, memory)
    n = len(seq); out = np.zeros_like(L)
    for t in range(n):
        if mode == 'plain': out[t] = L[t]; continue
        W = centres_world(seq, t)
        acc = np.zeros(len(W)); cnt = np.zeros(len(W)); fr = np.zeros(len(W))
        for s in range(t + 1):
            val = sample(np.clip(L[s], -clip, clip), seq, s, W)
            have = ~np.isnan(val)
            acc[have] += val[have]; cnt[have] += 1
            if free: fr += free_evidence(seq, s, W, margin, sil)
        f = np.where(cnt > 0, acc / np.maximum(cnt, 1), -clip)
        if free: f = np.where(fr > 0, f - free_w * clip * fr, f)
        out[t] = f.reshape(G.GRID_SHAPE)
    return out

def cut(seq, out):
    if 'support_plane' not in seq.meta: return out
    from grasp_client.wire import SupportPlane
    out = out.copy()
    for t in range(len(seq)):
        plane = SupportPlane.from_values(seq.meta['support_plane']).transformed(seq.camera_to_world[t])
        out[t][G.voxels_below_plane(seq.grid_to_camera[t], plane)] = -10
    return out

def score(seq, out, th=0.0):
    if CUT: out = cut(seq, out)
    js = [jac(out[t] >= th, seq.targets[t]) for t in range(len(seq))]
    return np.mean(js), js[-1], np.mean(js[-3:]) - np.mean(js[:3])

if __name__ == '__main__':
    split = sys.argv[1]; cond = sys.argv[2]
    files = sorted(glob.glob(f'/tmp/exp/{split}_{cond}_*.pkl'))
    seqs = [pickle.load(open(f, 'rb')) for f in files]
    configs = {
        'mvp': dict(mode='plain', memory=True),
        'off': dict(mode='plain', memory=False),
        'fuse_off': dict(mode='fuse', memory=False),
        'fuse_mem': dict(mode='fuse', memory=True),
        'fuse_off_free_obj': dict(mode='fuse', memory=False, free=True, sil=False),
        'fuse_off_free_sil': dict(mode='fuse', memory=False, free=True, sil=True),
        'fuse_mem_free_sil': dict(mode='fuse', memory=True, free=True, sil=True),
    }
    sel = sys.argv[3].split(',') if len(sys.argv) > 3 else list(configs)
    for name in sel:
        r = np.array([score(s, run(s, **configs[name])) for s in seqs])
        mo = [s.meta.get('camera_motion') for s in seqs]
        per = ' '.join(f'{m}:{r[[x == m for x in mo],0].mean():.3f}/{r[[x == m for x in mo],2].mean():+.3f}' for m in sorted(set(mo), key=str))
        print(per)
        print(f'{cond:10s} {name:22s} mean {r[:,0].mean():.3f} final {r[:,1].mean():.3f} rise {r[:,2].mean():+.3f} worst-final {r[:,1].min():.2f}', flush=True)

def run_world(seq, memory=True):
    from completion import evidence as E
    L = logits(seq, memory); out = np.zeros_like(L); ev = None
    for t in range(len(seq)):
        if ev is None: ev = E.RegisteredEvidence.around(seq.grid_to_camera[t], seq.camera_to_world[t])
        out[t] = ev.fuse(L[t], seq.grid_to_camera[t], seq.camera_to_world[t])
        ev.add(L[t], seq.grid_to_camera[t], seq.camera_to_world[t])
    return out
