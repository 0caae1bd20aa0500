"""grasp.evaluate.render: pictures of the hand on the mesh (pybullet TinyRenderer) and the command
line."""

from __future__ import annotations

import matplotlib.image
import numpy as np
import pytest
from grasp_scenes import scene_result

from grasp.evaluate.render import main, render_grasp


@pytest.fixture(scope="module")
def sphere_grasp():
    return scene_result("sphere_tripod")


def _color_fraction(image: np.ndarray, rgb, tol: int = 60) -> float:
    return float(np.mean(np.all(np.abs(image.astype(int) - np.array(rgb)) < tol, axis=2)))


def test_render_shows_object_and_hand_from_two_views(sphere_grasp):
    mesh, result = sphere_grasp
    images = render_grasp(mesh, result, width=160, height=120)
    assert len(images) == 2
    for image in images:
        assert image.shape == (120, 160, 3) and image.dtype == np.uint8
        assert _color_fraction(image, (217, 140, 77)) > 0.02  # the orange object
        assert _color_fraction(image, (191, 191, 204)) > 0.02  # the light-grey fingers
    assert not np.array_equal(images[0], images[1])


def test_command_line_plans_and_writes_a_png(tmp_path, capsys):
    mesh, _ = scene_result("box_small")
    path = tmp_path / "box.stl"
    mesh.export(path)
    out = tmp_path / "grasp.png"
    main([str(path), "--out", str(out), "--candidates", "4"])
    image = matplotlib.image.imread(out)
    assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 200
    assert "force closure" in capsys.readouterr().out


def test_bad_input(sphere_grasp, tmp_path):
    mesh, result = sphere_grasp
    with pytest.raises(ValueError, match="image size"):
        render_grasp(mesh, result, width=4, height=4)
    with pytest.raises(SystemExit):
        main([str(tmp_path / "missing.obj")])
