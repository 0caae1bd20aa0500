"""Will the grasp hold when the robot lifts the object off the table? A success model learned from
lift tests on training-split objects, for the planner's ranking on a table.

A force-closure grasp can still drop the object: too heavy for what the fingers press, held by
contacts above its centre of mass, wrapped by fingertips only. :func:`features` describes a
planned grasp by what the planner knows (the planned mesh, its contacts, the table), nothing of
the true object: the object's weight estimated from the planned shape (its volume at
``DENSITY_KG_M3``, the lift test's density) against what the grasp resists (the force epsilon
times the hand's grip), the grasp's kind (power or fingertip; from above or the side; a table
pinch), its
contacts' heights against the centre of mass, the fingers that touch. A logistic regression on
those (scikit-learn, standardised features) gives :func:`hold_probability`; its coefficients
live in ``grasp/ranking/lift_model.json`` and are applied here with numpy, so planning needs no
scikit-learn.

Its data and training: :mod:`grasp.evaluate.lift_training` (``python -m grasp.evaluate.lift_training
collect``, ``train``).
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import numpy as np

from grasp.hand.pinch import TABLE_PINCH
from grasp.physics.settings import DENSITY_KG_M3
from grasp_client.wire import SupportPlane

MODEL_PATH = Path(__file__).with_name("lift_model.json")
DATA_PATH = Path(__file__).with_name("lift_model_data.csv")
#: Nominal grip of the hand (N): three fingers pressing 20 N each (1 N·m at a 5 cm distal lever,
#: hands/barrett/README.md), what the force epsilon (per unit of contact force) is scaled by.
GRIP_N = 60.0
GRAVITY = 9.81
FEATURES: tuple[str, ...] = (
    "log_mass",  # log10 of the estimated mass (kg)
    "log_load",  # log10 of weight / (force epsilon × grip): above 0, more than the grip resists
    "force_epsilon",
    "epsilon",
    "palm",  # 1: the palm touches (a power grasp)
    "from_above",  # −approach · table normal: 1 straight down, 0 from the side
    "fingers",  # fingers with a contact (0–3)
    "breakaways",  # fingers whose proximal link stopped first
    "dof_gap",  # largest minus smallest finger DOF at the stop (degrees / 100): the first finger
    # to touch pushes the object alone until the others arrive
    "lowest_contact",  # lowest contact's height above the centre of mass (m)
    "mean_contact",  # mean contact height above the centre of mass (m)
    "size",  # the object's largest extent (m)
    "depth",  # centre of mass beyond the palm along the approach (m)
    "table_pinch",  # 1: a table pinch (grasp.hand.pinch), the palm rising while the fingers close
)


def estimated_mass(mesh, density: float = DENSITY_KG_M3) -> float:
    """The planned shape's mass (kg) at ``density``: its volume, or its convex hull's when the
    mesh is not closed."""
    volume = abs(float(mesh.volume)) if mesh.is_watertight else float(mesh.convex_hull.volume)
    return density * volume


def features(result, mesh, plane: SupportPlane, *, mass: float | None = None) -> np.ndarray:
    """(len(FEATURES),) of one autograsped, scored ``result`` on ``mesh`` resting on ``plane``."""
    mass = estimated_mass(mesh) if mass is None else mass
    center = np.asarray(mesh.center_mass if mesh.is_watertight else mesh.bounds.mean(axis=0))
    up = plane.normal
    heights = np.array([float((c.point - center) @ up) for c in result.contacts] or [0.0])
    fingers = {c.link[:2] for c in result.contacts if c.link.startswith("f")}
    fe = max(float(result.force_epsilon), 1e-3)
    pose = np.asarray(result.end_palm_pose)  # where the hand closed (a table pinch rose)
    return np.array([
        math.log10(max(mass, 1e-4)),
        math.log10(max(mass, 1e-4) * GRAVITY / (fe * GRIP_N)),
        float(result.force_epsilon),
        float(result.epsilon),
        float(any(c.link == "palm" for c in result.contacts)),
        float(-pose[:3, 2] @ up),
        float(len(fingers)),
        float(sum(s.startswith("breakaway") for s in result.finger_stops)),
        float(np.ptp(np.asarray(result.dofs_deg)[1:])) / 100.0,
        float(heights.min()),
        float(heights.mean()),
        float(np.max(mesh.extents)),
        float((center - pose[:3, 3]) @ pose[:3, 2]),
        float(result.kind == TABLE_PINCH),
    ])


@functools.lru_cache(maxsize=1)
def _model(path: str = str(MODEL_PATH)) -> dict | None:
    if not Path(path).exists():  # while the data for a first model are collected
        return None
    model = json.loads(Path(path).read_text())
    if tuple(model["features"]) != FEATURES:
        raise ValueError(f"{path} was trained on other features: {model['features']}")
    return model


def hold_probability(x: np.ndarray) -> np.ndarray:
    """(n,) probability that grasps with (n, len(FEATURES)) features hold in the lift test (NaN
    without a model file: the planner then ranks as without a table)."""
    m = _model()
    if m is None:
        return np.full(len(np.atleast_2d(x)), np.nan)
    z = (np.atleast_2d(x) - np.asarray(m["mean"])) / np.asarray(m["scale"])
    return 1.0 / (1.0 + np.exp(-(z @ np.asarray(m["coef"]) + m["intercept"])))
