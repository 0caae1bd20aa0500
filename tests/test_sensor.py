"""The sensor model's statistics match its parameters, on rendered planes and a box."""

import numpy as np
import pytest
import trimesh

from completion.depth_camera import Renderer, SensorModel, look_at

QUIET = {"edge_hole": 0.0, "edge_flying": 0.0, "subpixel": 0, "dropout": 0.0}


@pytest.fixture(scope="module")
def plane_depths():
    """Clean depth images of a wide plane seen square-on from 0.5, 0.8 and 1.0 m."""
    with Renderer() as r:
        r.add_mesh(trimesh.creation.box((3.0, 3.0, 0.01)).apply_translation([0, 0, -0.005]))
        return {z: r.render(look_at([0.0, 0.0, z], [0.0, 0.0, 0.0], up=(0, 1, 0)))[0]
                for z in (0.5, 0.8, 1.0)}


@pytest.fixture(scope="module")
def box_on_plane():
    """A 10 cm box standing on a plane, seen from 0.6 m above: depth edges all round it."""
    with Renderer() as r:
        r.add_mesh(trimesh.creation.box((3.0, 3.0, 0.01)).apply_translation([0, 0, -0.005]))
        r.add_mesh(trimesh.creation.box((0.1, 0.1, 0.1)).apply_translation([0, 0, 0.05]))
        return r.render(look_at([0.0, 0.0, 0.6], [0.0, 0.0, 0.0], up=(0, 1, 0)))


def test_noise_grows_with_depth_as_sigma_of_z(plane_depths):
    model = SensorModel(**QUIET)
    measured = []
    for z, depth in plane_depths.items():
        assert np.allclose(depth, z, atol=1e-3)  # the plane fills the image at distance z
        noisy = model.apply(depth, np.random.default_rng(0))
        residual = noisy.astype(np.float64) - depth
        measured.append(residual.std())
        assert residual.std() == pytest.approx(float(model.sigma(z)), rel=0.05), z
        assert abs(residual.mean()) < 0.1 * float(model.sigma(z))
    assert measured == sorted(measured)  # σ(0.5) < σ(0.8) < σ(1.0)


def test_quantization_steps_in_disparity(plane_depths):
    model = SensorModel(**{**QUIET, "subpixel": 8, "sigma_base": 0.0, "sigma_quadratic": 0.0})
    for z, depth in plane_depths.items():
        out = model.apply(depth, np.random.default_rng(0)).astype(np.float64)
        levels = np.unique(np.round(out, 7))
        # every depth is one of f·b / (k / 8): a whole number of 1/8-pixel disparity steps
        k = model.focal_px * model.baseline_m / levels * model.subpixel
        assert np.allclose(k, np.round(k), atol=1e-3)
        assert np.abs(out - depth).max() <= float(model.depth_step(z)) / 2 + 1e-4
    assert float(model.depth_step(1.0)) == pytest.approx(1 / (580 * 0.075 * 8))


def test_holes_and_flying_pixels_only_at_depth_edges(box_on_plane):
    depth, _ = box_on_plane
    model = SensorModel(**{**QUIET, "edge_hole": 0.3, "edge_flying": 0.15,
                           "sigma_base": 0.0, "sigma_quadratic": 0.0})
    on_edge, far = model.edges(depth)
    assert 100 < on_edge.sum() < 0.05 * depth.size  # the box's rim, 10 cm above the plane
    assert (far[on_edge] > depth[on_edge]).all()
    out = model.apply(depth, np.random.default_rng(1)).astype(np.float64)
    holes = out == 0
    moved = (out > 0) & (np.abs(out - depth) > 1e-6)
    assert not holes[~on_edge].any() and not moved[~on_edge].any()
    assert holes[on_edge].mean() == pytest.approx(0.3, abs=0.05)
    assert moved[on_edge].mean() == pytest.approx(0.15, abs=0.04)
    # a flying pixel lies between its surface and the far side of the edge, never beyond
    assert (out[moved] > depth[moved]).all() and (out[moved] <= far[moved] + 1e-6).all()


def test_dropout_fraction(plane_depths):
    model = SensorModel(**{**QUIET, "dropout": 0.02})
    out = model.apply(plane_depths[0.8], np.random.default_rng(2))
    assert (out == 0).mean() == pytest.approx(0.02, abs=0.004)


def test_the_sensor_is_deterministic_in_its_generator(box_on_plane):
    depth, _ = box_on_plane
    a = SensorModel().apply(depth, np.random.default_rng(5))
    b = SensorModel().apply(depth, np.random.default_rng(5))
    c = SensorModel().apply(depth, np.random.default_rng(6))
    assert a.tobytes() == b.tobytes() != c.tobytes()
    assert (a[depth == 0] == 0).all()  # no return stays no return


def test_sensor_parts_table_measures_every_part(capsys):
    """``python -m grasp.evaluate.sensor_parts`` on one sequence: every part, the noiseless one
    its own reference, voxel sides of real grids; the raw input is a separate, valid run."""
    from grasp.evaluate import sensor_parts

    table = sensor_parts.measure("completion/weights/mvp.pt", ["camera_pan"], 1, True, 1)
    assert list(table) == list(sensor_parts.PARTS)
    assert table["off"]["camera_pan"]["difference"] == 0.0
    for cells in table.values():
        assert 0.0 < cells["camera_pan"]["jaccard"] <= 1.0
        assert 1.0 < cells["camera_pan"]["voxel_mm"] < 20.0
    raw = sensor_parts.measure("completion/weights/mvp.pt", ["camera_pan"], 1, False, 1)
    off = raw["off"]["camera_pan"]["jaccard"]  # noiseless: the cleaning removes next to nothing
    assert off == pytest.approx(table["off"]["camera_pan"]["jaccard"], abs=0.02)
    assert raw["all of it"]["camera_pan"]["voxel_mm"] > table["all of it"]["camera_pan"]["voxel_mm"]
    with pytest.raises(SystemExit):
        sensor_parts.main(["--conditions", "nowhere"])
    assert "--conditions must name" in capsys.readouterr().err
