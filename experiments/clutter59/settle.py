import sys, numpy as np
from grasp.evaluate.clutter import scene_objects
from grasp.physics.world import DynamicWorld
from grasp.physics.settings import DEFAULT_SETTINGS
for i in map(int, sys.argv[1:]):
    tid, target, names, nbs, gaps, _ = scene_objects(i, 0)
    with DynamicWorld(target, table_top=0.0, neighbours=nbs) as w:
        far = np.eye(4); far[:3, 3] = [0, 0, 1.0]
        w.place_hand(far, [0.0] * 8)
        w.gravity(True)
        p0 = w.neighbour_poses()
        c = w.client
        t0 = c.getBasePositionAndOrientation(w.object_id)[0]
        for _ in range(int(2.0 / DEFAULT_SETTINGS.time_step)):
            w.step()
        p1 = w.neighbour_poses()
        t1 = c.getBasePositionAndOrientation(w.object_id)[0]
    moved = [float(np.linalg.norm(b[0] - a[0])) for a, b in zip(p0, p1)]
    print(i, tid, "target moved", round(100*np.linalg.norm(np.subtract(t1, t0)), 2), "cm; neighbours", list(zip(names, np.round(np.array(moved)*100, 2))))
