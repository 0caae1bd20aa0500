"""Second session on issue 58: do the six failing flat objects' pinches hold if they were heavier?"""
import sys, numpy as np
from grasp.evaluate.benchmark import benchmark_objects, resting_object, TABLE
from grasp.physics import lift_test
from grasp.physics.lift import DENSITY_KG_M3
from grasp.table import SupportPlane
from grasp.candidates import _footprint_axes, _palm_pose
from grasp.screen import open_hand_lowest
from grasp.pinch import TIP_CLEARANCE_M
from grasp.autograsp import autograsp
from grasp.collision import CollisionScene
SIX = ["proc/hammer/9", "proc/hammer/219", "proc/hammer/809", "proc/t_shape/639", "proc/cone/619", "urdf/990", "urdf/988"]
ids = benchmark_objects(100, 0)
table = SupportPlane(TABLE[:3], float(TABLE[3]))
for oid in sys.argv[1:] or SIX:
    mesh, _ = resting_object(oid, ids.index(oid), 0)
    vol = mesh.volume if mesh.is_watertight else mesh.convex_hull.volume
    scene = CollisionScene(mesh, support_plane=table)
    axes = _footprint_axes(mesh, table)[::-1]
    out = []
    for cname, center in (("bbox", mesh.bounds.mean(0)),):
        for ai, a in enumerate(axes):
            for spread in (0, 60):
                pose = _palm_pose(-table.normal, a, center, 0.3)
                travel = open_hand_lowest(table, pose[None], np.array([float(spread)]))[0] - TIP_CLEARANCE_M
                r = autograsp(scene, pose, spread_deg=spread, max_travel=travel, pinch=True)
                s = f"{'nar' if ai==0 else 'long'}/{spread}:{'FC' if r.success else '-'}"
                if r.success:
                    for k in (1, 10, 100):
                        L = lift_test(mesh, r, seed=0, support_plane=table, approach="guarded", density=DENSITY_KG_M3 * k)
                        s += f" x{k}:{'H' if L.success else 'D'}"
                out.append(s)
    print(f"{oid:20s} {1000*vol*DENSITY_KG_M3:.1f} g |", " | ".join(out), flush=True)
