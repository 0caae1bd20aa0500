"""``python -m grasp.evaluate``: the paper's evaluation (Tables I–III) in one command.

Scenes are generated on the fly, deterministically from ``--seed`` (:func:`make_sequence` of
every condition × {train, test} split, ``--count`` sequences each), every completion model runs
over each whole sequence (the parallel form, which is causal and equals streaming), and each view
is scored against its ground truth:

- Jaccard on the thresholded 40³ grids, and F-score@1% / @2% of the grid side of the meshed
  prediction against the true objects' surfaces inside the grid (independent dense samples;
  :mod:`grasp.evaluate.metrics`), averaged over the views of a sequence and then over sequences
  (Tables I and II), with the F-score ``ceiling``: the 40³ target itself scored the same way;
- grasp joint error on the final view of the single-object conditions (Table III): plan on the
  predicted mesh, re-grasp the *true object mesh* placed in the latest camera frame from the same
  pre-grasp pose (:func:`grasp.evaluate.metrics.grasp_joint_error`). The paper swaps in "the ground
  truth mesh"; we take the object's own mesh rather than a marching-cubes mesh of the 40³ target so
  that the error measures the completion, not the voxelisation of the ground truth.

Rows: the six models of the paper (single_view, mvp, mvt, lstm, mvp3, mvp6) and three
references: ``mvp_memory_off``, the shipped MVP given each view alone (a fresh memory every view:
MVP minus this row on the same sequences is what the memory adds, apart from training),
``prior``, one fixed shape per condition placed in every view's grid whatever the input
(:mod:`completion.prior`: what the grid's fit alone gives), and ``registered_fusion``, the union
of every view's observed voxels so far, mapped into the latest view's grid with the known camera
poses (what a user with a calibrated arm would do without a network; it assumes a static scene,
so it smears the sliding object of slide_behind). Grasp success (lift tests in pybullet) adds the
``true_mesh`` row: the grasp planned on the true mesh, executed like every other row's.
Every row is scored wherever the metric applies (the paper leaves Single-View N/A for the
conditions it did not train one on; a single-view model applies to every view of every
condition, so we report it). Cells are null only where a metric does not apply (the joint error
of the two-object conditions) or where no sequence of the cell gave a grasp to compare (an empty
completion has no surface to plan on; ``counts`` and ``grasp_failures`` in results.json say how
many and why).

Besides the main table: the held-out named pybullet_data objects (camera_pan, test only, one
sequence per object) and, with ``--objects DIR``, every OBJ/STL/PLY mesh in a folder.

Outputs in ``--out`` (default ``./evaluation/``): ``results.json``, ``results.md`` (the tables in
the paper's layout), ``jaccard_per_view.png`` (the memory story: Jaccard against view index per
condition and model), ``examples.png`` (final-view input, prediction of every row and ground
truth) and ``grasps.png`` (the planned grasp on the prediction and the re-grasp on the truth).

Cost (see :data:`PRESETS`): with trained models the grasping and the F-score meshes take about
equal shares. The default run evaluates 10 sequences per condition and split, grasps every
single-object one with the planner's 24 principal-axis candidates and lift-tests 5 per cell (the
README gives its measured time); ``--quick`` is a one-minute smoke test; ``--full`` uses 50
sequences per cell and the planner's 64 candidates. Stage timings are printed at the end:
each stage's seconds summed over sequences (so over all worker processes), and the wall time of
the whole run.

Determinism: scenes, surface samples and planner candidates are seeded from ``--seed`` and the
sequence's identity, and every worker runs torch on one thread, so the numbers do not depend on
``--workers``.

The package: :mod:`~grasp.evaluate.config` (rows, metrics, presets, settings, the paper's
numbers), :mod:`~grasp.evaluate.rows` (each row an object that turns views into probabilities),
:mod:`~grasp.evaluate.sequence_result` (a sequence's result, stage timings),
:mod:`~grasp.evaluate.runner` (one sequence), :mod:`~grasp.evaluate.pool` (the workers),
:mod:`~grasp.evaluate.tables` (every table, one module each with its options: main, sensor,
overhead, benchmark, clutter, objects), :mod:`~grasp.evaluate.aggregate` (the main tables' cells
and counts), :mod:`~grasp.evaluate.precision` (Table I's standard errors),
:mod:`~grasp.evaluate.results_json` (all of results.json), :mod:`~grasp.evaluate.cells` (means and
their Markdown), :mod:`~grasp.evaluate.results_md` (results.md), :mod:`~grasp.evaluate.figures`
and :mod:`~grasp.evaluate.failure_figures` (the PNGs), :mod:`~grasp.evaluate.benchmark_scenes`
and :mod:`~grasp.evaluate.clutter_scenes` (the benchmark's and the clutter table's scenes and
rows) and :mod:`~grasp.evaluate.cli` (the command line).
"""

from grasp.evaluate.aggregate import aggregate
from grasp.evaluate.cli import build_parser, evaluate, main, settings_from_args
from grasp.evaluate.config import (
    CONDITIONS,
    FUSION,
    MAIN_TABLE,
    MEMORY_OFF,
    MODEL_NAMES,
    PRESETS,
    PRIOR,
    REGISTERED,
    ROWS,
    TRUE_MESH,
    Job,
    Settings,
)
from grasp.evaluate.pool import run_jobs
from grasp.evaluate.results_json import build_results
from grasp.evaluate.results_md import markdown_report
from grasp.evaluate.rows import registered_fusion
from grasp.evaluate.runner import Evaluator, make_jobs

__all__ = [
    "CONDITIONS",
    "FUSION",
    "MAIN_TABLE",
    "MEMORY_OFF",
    "MODEL_NAMES",
    "PRESETS",
    "PRIOR",
    "REGISTERED",
    "ROWS",
    "TRUE_MESH",
    "Evaluator",
    "Job",
    "Settings",
    "aggregate",
    "build_parser",
    "build_results",
    "evaluate",
    "main",
    "make_jobs",
    "markdown_report",
    "registered_fusion",
    "run_jobs",
    "settings_from_args",
]
