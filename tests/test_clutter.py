"""The clutter table's scenes (grasp.evaluate.clutter_scenes, issue 61): a target among neighbours
at gaps that matter to the hand, what the camera sees of the neighbours, and the table's rows."""

from __future__ import annotations

import numpy as np
import pytest

from grasp.evaluate import clutter_scenes as c


def _gap(a, b) -> float:
    return c._gap(c._footprint(a, 0), c._footprint(b, 0))


@pytest.mark.parametrize("index", [0, 3])
def test_neighbours_stand_2_to_10_cm_from_the_target_and_apart(index):
    target_id, target, ids, neighbours, gaps, _ = c.scene_objects(index, 0)
    assert c.NEIGHBOURS[0] <= len(neighbours) <= c.NEIGHBOURS[1] and target_id not in ids
    for mesh, gap in zip(neighbours, gaps, strict=True):
        assert c.GAP_M[0] <= gap <= c.GAP_M[1]
        assert abs(_gap(target, mesh) - gap) < 0.005  # measured on other samples of the surface
        assert abs(mesh.bounds[0, 2]) < 1e-6 and max(mesh.extents) <= c.MAX_NEIGHBOUR_M
    for i in range(len(neighbours)):
        for j in range(i):
            assert _gap(neighbours[i], neighbours[j]) >= c.GAP_M[0] - 0.005
    again = c.scene_objects(index, 0)
    assert again[2] == ids and all(np.allclose(a.vertices, b.vertices)
                                   for a, b in zip(again[3], neighbours, strict=True))


def test_the_obstacles_seen_are_the_neighbours_not_the_target():
    from trimesh.proximity import closest_point

    from completion.depth_camera import Renderer

    renderer = Renderer()
    try:
        scene = c.clutter_scene(0, 0, renderer)
    finally:
        renderer.close()
    assert scene.mask.any(axis=(1, 2)).all()  # the target is in every view
    assert not (scene.mask & scene.others).any()
    seen = c.seen_obstacles(scene)
    assert len(seen) > 100
    to_target = closest_point(scene.target, seen.centres)[1]
    to_neighbours = np.min([closest_point(m, seen.centres)[1] for m in scene.neighbours], axis=0)
    assert np.median(to_neighbours) < 0.01  # the sensor's noise and the voxels' pitch
    assert (to_target > 0.01).mean() > 0.95


def test_the_failures_figure_colours_target_neighbours_and_table_apart(tmp_path):
    """clutter_failures.png's panels: the target orange, a neighbour blue, the table green, seen
    from above the table, with a legend; the heading wrapped to the figure's width."""
    from types import SimpleNamespace

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import trimesh
    from PIL import Image

    from grasp.evaluate.failure_figures import failures_figure
    from grasp.planner import plan
    from grasp_client.wire import SupportPlane

    target = trimesh.creation.box(extents=[0.06, 0.05, 0.08])
    target.apply_translation([0.0, 0.0, 0.04])
    neighbour = trimesh.creation.box(extents=[0.05, 0.05, 0.1])
    neighbour.apply_translation([0.12, 0.0, 0.05])
    best = plan(target, n_candidates=16, seed=0, top_k=1,
                support_plane=SupportPlane(np.array([0.0, 0.0, 1.0]), 0.0))[0]
    record = {"success": False, "reason": "a neighbour moved 4 cm", "kind": best.kind,
              "palm_pose": np.asarray(best.palm_pose).tolist(),
              "planned_joints_deg": list(best.joints_deg)}
    raw = [SimpleNamespace(job=SimpleNamespace(table="clutter", index=0), object_ids=["box"],
                           record={"rows": {"row": record}})]
    heading = "Clutter: a heading far longer than one panel is wide, which must wrap " * 2
    path = failures_figure(raw, tmp_path, plt, "clutter", "row", lambda r: [target, neighbour],
                           lambda r, o: "box: ", heading, "clutter_failures.png", key="success")
    image = np.asarray(Image.open(path).convert("RGB"), dtype=int)
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    assert ((r - b > 80) & (r > 150)).sum() > 200  # the target's orange
    assert ((b - r > 60) & (b > 150)).sum() > 200  # the neighbour's blue
    assert ((g - r > 15) & (g - b > 15)).sum() > 1000  # the table's green
