"""What an evaluation run is: its rows, conditions, metrics, presets, settings and jobs, and the
paper's numbers to print beside ours."""

from __future__ import annotations

from dataclasses import dataclass

from completion.config import POSED_MODEL
from completion.scenes import CONDITIONS, VIEWS

MODEL_NAMES: tuple[str, ...] = ("single_view", "mvp", "mvt", "lstm", "mvp3", "mvp6")
#: The input-free reference row (:mod:`completion.prior`): a fixed shape in every view's grid.
PRIOR = "prior"
FUSION = "registered_fusion"
#: The ablation row: the shipped MVP given each view alone (a fresh memory every view), so that
#: MVP minus this row, on the same sequences, is what the memory adds and nothing else.
MEMORY_OFF = "mvp_memory_off"
#: The shipped MVP streamed as the service streams a session whose views carry camera poses: each
#: view's logits averaged with the earlier views' in the world frame (completion.evidence).
REGISTERED = "mvp_registered"
#: Rows that are not learned models of their own (never bold in the tables).
REFERENCE_ROWS: tuple[str, ...] = (MEMORY_OFF, PRIOR, FUSION)
ROWS: tuple[str, ...] = (*MODEL_NAMES, REGISTERED, *REFERENCE_ROWS)
ROW_LABELS = {
    "single_view": "Single-View",
    "mvp": "MVP",
    "mvt": "MVT",
    "lstm": "LSTM",
    "mvp3": "MVP3",
    "mvp6": "MVP6",
    REGISTERED: "MVP + camera poses (registered evidence)",
    MEMORY_OFF: "MVP, memory off: each view alone (ref.)",
    PRIOR: "Prior, ignores the input (ref.)",
    FUSION: "Registered fusion (ref.)",
    "true_mesh": "True mesh (planned on the truth)",
}
#: The grasp-success row of grasps planned on the true mesh itself, executed like every row.
TRUE_MESH = "true_mesh"
#: Column order of the paper's tables.
PAPER_ORDER: tuple[str, ...] = (
    "object_hiding",
    "object_reveal",
    "camera_pan",
    "slide_behind",
    "two_object_pan",
)
CONDITION_LABELS = {
    "object_hiding": "Object Hiding",
    "object_reveal": "Object Reveal",
    "camera_pan": "Camera Pan",
    "slide_behind": "Slide Behind Other",
    "two_object_pan": "Two Object Pan",
    "tabletop": "Tabletop (ours)",
}
#: Column order of our tables: the paper's five, then the product's own tabletop condition.
TABLE_ORDER: tuple[str, ...] = (*PAPER_ORDER, "tabletop")
EVAL_SPLITS: tuple[str, ...] = ("train", "test")
METRICS: tuple[str, ...] = (
    "jaccard",
    "fscore_1",
    "fscore_2",
    "joint_error_deg",
    "joint_error_moving_deg",
)
#: Metrics of the grasp on the final view (single-object conditions only).
JOINT_METRICS: tuple[str, ...] = ("joint_error_deg", "joint_error_moving_deg")
FSCORE_METRICS: tuple[str, ...] = ("fscore_1", "fscore_2")
METRIC_TITLES = {
    "jaccard": "Table I: Jaccard (mean over views; higher is better)",
    "fscore_1": "Table II: F-score@1% (mean over views; higher is better)",
    "fscore_2": "F-score@2% (mean over views; higher is better)",
    "joint_error_deg": "Table III: grasp joint error, degrees, mean over the 8 joints as in the "
    "paper (final view; lower is better)",
    "joint_error_moving_deg": "Grasp joint error, degrees, mean over the 6 joints that move "
    "(final view; lower is better)",
}
HIGHER_IS_BETTER = {
    "jaccard": True,
    "fscore_1": True,
    "fscore_2": True,
    "joint_error_deg": False,
    "joint_error_moving_deg": False,
    "grasp_success": True,
}
#: Lift-test success rate (pybullet dynamics, final view of the single-object conditions).
GRASP_SUCCESS = "grasp_success"
GRASP_SUCCESS_TITLE = (
    "Grasp success: planned on the prediction, lifted and shaken on the true object in pybullet "
    "(final view; higher is better)"
)
#: The main table's name (each other table's is in its module, grasp.evaluate.tables).
MAIN_TABLE = "main"
#: The paper's Tables I–III, (train, test) per condition in PAPER_ORDER; None = N/A there.
_PAPER_ROWS = {
    "jaccard": {
        "single_view": (None, None, (0.91, 0.88), None, (0.90, 0.87)),
        "mvp": ((0.90, 0.87), (0.80, 0.78), (0.96, 0.90), (0.97, 0.95), (0.93, 0.89)),
        "mvt": ((0.90, 0.86), (0.80, 0.78), (0.95, 0.90), (0.97, 0.95), (0.92, 0.88)),
        "lstm": ((0.90, 0.86), (0.80, 0.77), (0.93, 0.90), (0.97, 0.95), (0.92, 0.88)),
        "mvp3": ((0.89, 0.86), (0.78, 0.76), (0.92, 0.90), (0.95, 0.94), (0.91, 0.88)),
        "mvp6": ((0.89, 0.87), (0.79, 0.77), (0.93, 0.90), (0.96, 0.95), (0.92, 0.88)),
    },
    "fscore_1": {
        "single_view": (None, None, (0.90, 0.87), None, (0.90, 0.87)),
        "mvp": ((0.90, 0.86), (0.75, 0.71), (0.95, 0.90), (0.97, 0.95), (0.92, 0.88)),
        "mvt": ((0.90, 0.85), (0.75, 0.71), (0.94, 0.90), (0.97, 0.95), (0.91, 0.87)),
        "lstm": ((0.90, 0.85), (0.75, 0.69), (0.92, 0.90), (0.97, 0.95), (0.92, 0.87)),
        "mvp3": ((0.89, 0.86), (0.72, 0.70), (0.91, 0.88), (0.95, 0.94), (0.91, 0.87)),
        "mvp6": ((0.88, 0.85), (0.74, 0.72), (0.92, 0.90), (0.96, 0.95), (0.91, 0.88)),
    },
    "joint_error_deg": {
        "single_view": (None, None, (4.57, 4.62), None, None),
        "mvp": ((4.10, 4.16), (3.80, 3.94), (3.75, 3.83), None, None),
        "mvt": ((4.14, 4.19), (3.85, 3.98), (3.79, 3.84), None, None),
        "lstm": ((4.15, 4.22), (3.88, 3.97), (3.82, 3.89), None, None),
        "mvp3": ((4.23, 4.28), (4.00, 4.09), (3.98, 4.05), None, None),
        "mvp6": ((4.18, 4.22), (3.94, 3.99), (3.92, 3.98), None, None),
    },
}
PAPER_TABLES: dict = {
    metric: {
        row: {
            c: {"train": None if v is None else v[0], "test": None if v is None else v[1]}
            for c, v in zip(PAPER_ORDER, values, strict=True)
        }
        for row, values in rows.items()
    }
    for metric, rows in _PAPER_ROWS.items()
}
"""The paper's numbers in the layout of results.json's ``tables`` (for side-by-side reports)."""
#: Decision threshold of a checkpoint that does not store one.
DEFAULT_THRESHOLD = 0.5


@dataclass(frozen=True)
class Measured:
    """One run's wall time on the project's machine: what --help, the README and
    docs/performance.md quote for a preset (tests/test_timings.py checks that they agree)."""

    wall_s: float
    command: str
    when: str  # the date and commit of the run

    @property
    def text(self) -> str:
        """The figure as every page quotes it: ``"889 s (14.8 min)"``."""
        return f"{self.wall_s:.0f} s ({self.wall_s / 60:.1f} min)"


#: The machine the :data:`MEASURED` runs ran on.
MEASURED_ON = "2 cores (AMD EPYC), 2 worker processes, nothing else running"
#: Wall time of a preset's run (the process, ``/usr/bin/time``), measured once on
#: :data:`MEASURED_ON`; re-measure and update the README and docs/performance.md with it when a
#: change moves it. ``--full`` is not measured.
MEASURED: dict[str, Measured] = {
    "default": Measured(889.4, "python -m grasp.evaluate", "2026-12-08, main f5f1eee"),
    "quick": Measured(133.4, "python -m grasp.evaluate --quick", "2026-12-08, main f5f1eee"),
}


@dataclass(frozen=True)
class Preset:
    """The main table's sizes in a run: sequences per (condition, split), grasped and lift-tested
    ones, planner candidates (the other tables' options give theirs per preset themselves:
    :class:`grasp.evaluate.tables.base.Option`)."""

    count: int
    candidates: int
    grasp_count: int  # test sequences grasped per single-object condition (beyond count: only
    # grasped); the train split grasps at most count
    physics_count: int  # of the grasped test ones, how many are lift-tested in pybullet


#: Sizes per preset. What each stage costs is in every run's results.md (its Timings section:
#: wall and CPU seconds per stage, summed over sequences) and docs/performance.md;
#: :data:`MEASURED` holds the wall times the docs quote.
PRESETS: dict[str, Preset] = {
    # A smoke test of the whole chain (MEASURED["quick"]).
    "quick": Preset(count=2, candidates=8, grasp_count=2, physics_count=1),
    # The command with no arguments (MEASURED["default"]): 120 sequences (10 per condition
    # and split), all 80 single-object ones grasped with 24 candidates (the planner's 24
    # principal-axis poses) and 10 more test sequences per single-object condition grasped only
    # (20 grasps per test cell, so that one grasp cannot swing the joint error), 5 of them per
    # test cell lift-tested, and the other tables at their own defaults (tables.base.Option:
    # 5 named objects, the sensor table's 5 test sequences per condition, the grasp benchmark's
    # 30 objects, 10 of them with the verified rows, ...).
    "default": Preset(count=10, candidates=24, grasp_count=20, physics_count=5),
    # Not measured (estimated at about 40 minutes on two cores; use --workers on a bigger
    # machine): 50 sequences per cell and the planner's full 64 candidates.
    "full": Preset(count=50, candidates=64, grasp_count=50, physics_count=10),
}


#: Rows shown in grasps.png (the first ones present): the paper's model, a baseline, the reference.
GRASP_FIGURE_ROWS: tuple[str, ...] = ("mvp", "single_view", FUSION)


def figure_rows(rows: list[str]) -> list[str]:
    """The rows whose grasps the figure draws (:data:`GRASP_FIGURE_ROWS`, or the first row)."""
    return [n for n in GRASP_FIGURE_ROWS if n in rows] or rows[:1]


def checkpoints_needed(rows) -> list[str]:
    """The models whose checkpoints these rows run: the model rows, MVP for its memory-off and
    registered rows, and the posed model for the registered row."""
    needed = [n for n in MODEL_NAMES
              if n in rows or (n == "mvp" and (MEMORY_OFF in rows or REGISTERED in rows))]
    return needed + [POSED_MODEL] if REGISTERED in rows else needed


def checkpoints_loaded(rows) -> list[str]:
    """:func:`checkpoints_needed`, and the posed model wherever MVP runs: the grasp benchmark's and
    the clutter table's MVP rows stream posed views as the service does (it runs the posed model
    for them)."""
    needed = checkpoints_needed(rows)
    return needed + [POSED_MODEL] if "mvp" in needed and POSED_MODEL not in needed else needed


@dataclass(frozen=True)
class Settings:
    """Everything a run depends on (written to results.json as ``config``)."""

    rows: tuple[str, ...] = ROWS
    model_paths: tuple[tuple[str, str], ...] = ()  # (name, checkpoint path) per model row
    prior_path: str = ""  # the prior row's file (completion/weights/prior.npz)
    conditions: tuple[str, ...] = CONDITIONS
    count: int = PRESETS["default"].count
    grasp_count: int = PRESETS["default"].grasp_count
    physics_count: int = PRESETS["default"].physics_count
    objects: tuple[str, ...] = ()  # file: ids of --objects DIR
    views: int = VIEWS
    seed: int = 0
    candidates: int = PRESETS["default"].candidates
    samples: int = 8192
    workers: int = 1
    ray: bool = False  # run the workers as Ray actors (completion.cluster)
    examples: bool = True
    #: (name, value) of the tables' own options (:class:`grasp.evaluate.tables.base.Option`,
    #: read with its ``of``); an option not named here has its default. Checked against the
    #: tables when a run plans its jobs (:func:`grasp.evaluate.tables.check_options`), as the
    #: tables import this module
    options: tuple[tuple[str, int], ...] = ()

    def __post_init__(self) -> None:
        unknown = [r for r in self.rows if r not in ROWS]
        if unknown or not self.rows:
            raise ValueError(f"rows must be a non-empty subset of {ROWS}, got {self.rows}")
        bad = [c for c in self.conditions if c not in CONDITIONS]
        if bad:
            raise ValueError(f"conditions must be among {CONDITIONS}, got {bad}")
        missing = [r for r in checkpoints_needed(self.rows) if r not in dict(self.model_paths)]
        if missing:
            raise ValueError(f"no checkpoint path given for model rows {missing}")
        if PRIOR in self.rows and not self.prior_path:
            raise ValueError("the prior row needs prior_path (completion/weights/prior.npz)")
        for name in (
            "count",
            "grasp_count",
            "physics_count",
            "candidates",
            "samples",
            "workers",
        ):
            least = 1 if name in ("candidates", "samples", "workers") else 0
            if getattr(self, name) < least:
                raise ValueError(f"{name} out of range: {getattr(self, name)}")
        if self.views < 2:
            raise ValueError(f"views must be >= 2, got {self.views}")


@dataclass(frozen=True)
class Job:
    """One sequence to evaluate."""

    table: str  # the name of the table that asked for it (grasp.evaluate.tables)
    condition: str
    split: str
    index: int
    pool: tuple[str, ...] | None = None  # object ids to draw from (None: the split's library)
    grasp: bool = False
    grasp_only: bool = False  # beyond the table's count: grasped, in no completion table
    example: bool = False
    physics: bool = False  # also lift-test the grasps in pybullet (grasped jobs only)
    noise: bool | None = None  # the sensor model (None: the condition's default)
    light: bool = False  # Jaccard (and the share below the table) only: no F-score, no grasp
