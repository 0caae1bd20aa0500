"""grasp.evaluate.rows: every row one object that turns a sequence's views into probabilities, with
its threshold; the memory-off row is the model given each view alone; the fusion the benchmark
uses is the same function as the fusion row's."""

from __future__ import annotations

import numpy as np

import grasp.evaluate as ev
from completion.model import WEIGHTS_DIR
from completion.prior import PRIOR_FILE
from completion.scenes import make_sequence
from grasp.evaluate.rows import FusionRow, MemoryOffRow, ModelRow, PriorRow, load_models, make_rows


def test_rows_turn_views_into_probabilities(tiny_model):
    settings = ev.Settings(rows=("mvp", ev.MEMORY_OFF, ev.PRIOR, ev.FUSION),
                           model_paths=(("mvp", tiny_model),),
                           prior_path=str(WEIGHTS_DIR / PRIOR_FILE))
    rows = make_rows(settings, load_models(settings))
    assert list(rows) == list(settings.rows)
    assert [type(r) for r in rows.values()] == [ModelRow, MemoryOffRow, PriorRow, FusionRow]
    seq = make_sequence("camera_pan", "test", 0, seed=0, views=3)
    out = {name: row.probabilities(seq) for name, row in rows.items()}
    assert all(p.shape == (3, 40, 40, 40) for p in out.values())
    for t in range(3):  # memory off: view t alone is a sequence of one view
        alone = make_sequence("camera_pan", "test", 0, seed=0, views=3)
        alone.inputs = seq.inputs[t:t + 1]
        np.testing.assert_allclose(out[ev.MEMORY_OFF][t], rows["mvp"].probabilities(alone)[0],
                                   atol=1e-6)
    np.testing.assert_array_equal(out[ev.FUSION][0], seq.inputs[0])  # one view: what it saw
    assert rows[ev.FUSION].threshold("camera_pan") == 0.5
    assert rows[ev.MEMORY_OFF].threshold("x") == rows["mvp"].threshold("y")
    assert rows[ev.PRIOR].threshold("camera_pan") == rows[ev.PRIOR].prior.thresholds["camera_pan"]
