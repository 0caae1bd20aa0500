"""Candidate variants for table pinches, measured on training-split flat objects (not the benchmark's).
Usage: python flat_train.py VARIANT [N]  -- prints one line per flat object and a total."""
import sys, zlib, json, numpy as np
import grasp.candidates as C
from completion.objects import object_ids, load_object
from completion.scenes import stable_pose
from grasp.planner import plan
from grasp.physics import lift_test
from grasp.pinch import pinch_height, TABLE_PINCH, TIP_CLEARANCE_M
from grasp.table import SupportPlane
from grasp.screen import open_hand_lowest
FLOOR = SupportPlane(np.array([0, 0, 1.0]), 0.0)
variant = sys.argv[1]
N = int(sys.argv[2]) if len(sys.argv) > 2 else 40
orig = C.table_candidates
def patched(mesh, plane, **kw):
    out = orig(mesh, plane, **kw)
    if variant == "base":
        return out
    if variant == "none":
        return [c for c in out if c.source != TABLE_PINCH]
    pinches = [c for c in out if c.source == TABLE_PINCH]
    rest = [c for c in out if c.source != TABLE_PINCH]
    if not pinches:
        return out
    axes = C._footprint_axes(mesh, plane)[::-1]
    center = mesh.bounds.mean(axis=0)
    if variant == "com" and mesh.is_watertight:
        center = np.array(mesh.center_mass)
    spreads = (0.0, 60.0) if variant == "com" else (0.0, 60.0, 90.0)
    new = []
    for a in axes:
        for s in spreads:
            pose = C._palm_pose(-plane.normal, a, center, 0.3)
            travel = open_hand_lowest(plane, pose[None], np.array([s]))[0] - TIP_CLEARANCE_M
            new.append(C.Candidate(pose, s, TABLE_PINCH, float(travel)))
    return rest[:4] + new + rest[4:]
import grasp.planner as P
P.table_candidates = patched
ids = object_ids("train")
order = np.random.default_rng(5).permutation(len(ids))
held = tried = nog = 0
for k in order:
    oid = ids[k]
    mesh = load_object(oid)
    rng = np.random.default_rng([0, zlib.crc32(oid.encode())])
    pose, _ = stable_pose(mesh, oid, rng)
    mesh = mesh.copy().apply_transform(pose)
    if mesh.bounds[1, 2] >= pinch_height() or max(mesh.extents) > 0.3:
        continue
    g = plan(mesh, n_candidates=64, seed=0, top_k=1, support_plane=FLOOR)[0]
    tried += 1
    if not g.success:
        nog += 1; print(oid, "no grasp", g.reason[:60], flush=True)
    else:
        L = lift_test(mesh, g, seed=0, support_plane=FLOOR, approach="guarded")
        held += L.success
        print(oid, g.kind, L.success, flush=True)
    if tried >= N:
        break
print(f"TOTAL {variant}: held {held}/{tried}, no grasp {nog}")
