"""One truth for planner and executor: a grasp planned on a table is executed the way it was
planned (guarded, :func:`grasp.physics.lift.lift_test`), low and heavy objects, and the lift model
that ranks grasps on a table."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from grasp.physics.lift import lift_test
from grasp.physics.settings import DEFAULT_SETTINGS
from grasp.planner import plan
from grasp.ranking.rank import HOLD_THRESHOLD
from grasp_client.wire import SupportPlane

FLOOR = SupportPlane(np.array([0.0, 0.0, 1.0]), 0.0)  # the table z = 0


def on_table(*extents: float) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=extents)
    return box.apply_translation([0.0, 0.0, extents[2] / 2])


def test_a_box_lying_on_a_table_is_executed_as_planned():
    """Planned with the table, executed as the benchmark executes (guarded, from the table, lift
    and shake): the fingers end where the planner said, within 2°, and the box is held."""
    box = on_table(0.12, 0.08, 0.05)
    grasp = plan(box, n_candidates=64, seed=0, top_k=1, support_plane=FLOOR)[0]
    assert grasp.success and grasp.approach_stop == "contact", grasp.reason
    lifted = lift_test(box, grasp, seed=0, support_plane=FLOOR, approach="guarded")
    assert lifted.success, lifted.reason
    gap = np.abs(np.asarray(grasp.joints_deg) - lifted.joints_deg)
    assert gap.max() <= 2.0, (np.asarray(grasp.joints_deg).round(1), lifted.joints_deg.round(1))


def test_a_2cm_box_gets_a_fingertip_grasp_that_holds():
    """12 × 6 × 2 cm: a pinch from above whose tips sweep just over the table; its approach ends
    untouched at the planned pose, and the guarded execution stops there too."""
    box = on_table(0.12, 0.06, 0.02)
    grasp = plan(box, n_candidates=64, seed=0, top_k=1, support_plane=FLOOR)[0]
    assert grasp.success, grasp.reason
    assert grasp.approach_stop == "limit" and grasp.palm_pose[2, 2] < -0.99  # from above
    lifted = lift_test(box, grasp, seed=0, support_plane=FLOOR, approach="guarded")
    assert lifted.success, lifted.reason
    assert lifted.travel == pytest.approx(DEFAULT_SETTINGS.pregrasp_backoff, abs=1e-3)


def test_a_heavy_wide_box_gets_a_grasp_that_holds_or_the_reason_none_can():
    box = on_table(0.20, 0.20, 0.06)  # 1.2 kg at 500 kg/m³
    grasp = plan(box, n_candidates=64, seed=0, top_k=1, support_plane=FLOOR)[0]
    if grasp.success:
        assert lift_test(box, grasp, seed=0, support_plane=FLOOR, approach="guarded").success
    else:
        assert "wider than the 11 cm the fingertips close to" in grasp.reason, grasp.reason
        assert "20 × 20 cm on the table and 6 cm tall" in grasp.reason


def test_a_grasp_predicted_to_drop_is_a_failure_that_says_so():
    """Every force-closure grasp on a table carries the lift model's probability; those below
    the threshold come back as failures with the estimated mass."""
    heavy = on_table(0.26, 0.26, 0.20)  # 6.8 kg at 500 kg/m³
    grasps = plan(heavy, n_candidates=64, seed=0, top_k=None, support_plane=FLOOR)
    scored = [g for g in grasps if not np.isnan(g.hold_probability)]
    assert any(g.hold_probability < HOLD_THRESHOLD for g in scored)
    for g in scored:
        assert 0.0 <= g.hold_probability <= 1.0
        if g.hold_probability < HOLD_THRESHOLD:
            assert not g.success and "predicted to drop" in g.reason and "6.76 kg" in g.reason
        else:
            assert g.success
    floating = plan(heavy, n_candidates=64, seed=0, top_k=3)  # no table: no lift model
    assert all(np.isnan(g.hold_probability) for g in floating)


def test_the_lift_model_is_what_its_data_and_command_give(tmp_path):
    """The committed coefficients are `python -m grasp.evaluate.lift_training train` on the
    committed data (training-split objects only), and the features are the ones it was trained
    on."""
    from completion.objects import object_ids
    from grasp.evaluate.lift_training import main
    from grasp.ranking.lift_model import DATA_PATH, FEATURES, MODEL_PATH

    out = tmp_path / "model.json"
    main(["train", "--data", str(DATA_PATH), "--out", str(out)])
    fresh, shipped = json.loads(out.read_text()), json.loads(MODEL_PATH.read_text())
    assert fresh["features"] == shipped["features"] == list(FEATURES)
    np.testing.assert_allclose(fresh["coef"], shipped["coef"], atol=1e-6)
    assert fresh["cv_top_grasp_held"] == shipped["cv_top_grasp_held"]
    trained_on = {line.split(",")[0] for line in DATA_PATH.read_text().splitlines()[1:]}
    assert trained_on <= set(object_ids("train"))  # never a benchmark (test-split) object
