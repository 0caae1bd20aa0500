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
