"""Will the grasp hold when the robot lifts the object off the table? A success model learned from
lift tests on training-split objects, for the planner's ranking on a table.

A force-closure grasp can still drop the object: too heavy for what the fingers press, held by
contacts above its centre of mass, wrapped by fingertips only. :func:`features` describes a
planned grasp by what the planner knows (the planned mesh, its contacts, the table), nothing of
the true object: the object's weight estimated from the planned shape (its volume at
``DENSITY_KG_M3``, the lift test's density) against what the grasp resists (the force epsilon
times the hand's grip), the grasp's kind (power or fingertip; from above or the side), its
contacts' heights against the centre of mass, the fingers that touch. A logistic regression on
those (scikit-learn, standardised features) gives :func:`hold_probability`; its coefficients
live in ``grasp/lift_model.json`` and are applied here with numpy, so planning needs no
scikit-learn.

The data: ``python -m grasp.lift_model collect`` rests training-split objects (never the
benchmark's, which are held out) on a table in a stable pose, plans on the true mesh with the
table, and lift-tests every force-closure grasp the planner ranks (guarded execution, as the
benchmark) — ``grasp/lift_model_data.csv``, one row per grasp. ``python -m grasp.lift_model
train`` fits the model and writes the JSON with its cross-validated figures (grouped by object).
"""

from __future__ import annotations

import argparse
import csv
import functools
import json
import math
import time
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from grasp.physics.settings import DENSITY_KG_M3
from grasp.table import SupportPlane

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
    pose = np.asarray(result.palm_pose)
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


# -- data and training ---------------------------------------------------------------------------
def _collect_one(job: tuple[int, str, int]) -> list[dict]:
    from completion.objects import load_object
    from completion.scenes import stable_pose
    from grasp.physics import lift_test
    from grasp.planner import plan

    index, object_id, seed = job
    rng = np.random.default_rng([seed, zlib.crc32(b"lift_model/scene"), index])
    mesh = load_object(object_id)
    pose, _ = stable_pose(mesh, object_id, rng)
    world = mesh.copy().apply_transform(pose)
    table = SupportPlane(np.array([0.0, 0.0, 1.0]), 0.0)
    rows = []
    for rank, grasp in enumerate(plan(world, seed=index, top_k=None, support_plane=table)):
        if not grasp.success:
            break
        lifted = lift_test(world, grasp, seed=index, table=True, approach="guarded")
        x = features(grasp, world, table)
        rows.append({"object_id": object_id, "rank": rank, "held": int(lifted.success),
                     **{name: round(float(v), 6) for name, v in zip(FEATURES, x, strict=True)}})
    return rows


def collect(count: int, seed: int, out: Path, workers: int) -> None:
    """Lift-test the ranked force-closure grasps of ``count`` training-split objects on a table."""
    from multiprocessing import Pool

    from completion.objects import object_ids

    pool = object_ids("train")
    order = np.random.default_rng([seed, zlib.crc32(b"lift_model")]).permutation(len(pool))
    jobs = [(i, pool[k], seed) for i, k in enumerate(order[:count])]
    start = time.perf_counter()
    with Pool(workers) as p, out.open("w", newline="") as f:
        writer = csv.DictWriter(f, ["object_id", "rank", "held", *FEATURES])
        writer.writeheader()
        for n, rows in enumerate(p.imap(_collect_one, jobs), 1):
            writer.writerows(rows)
            print(f"{n}/{count} objects, {time.perf_counter() - start:.0f} s", flush=True)


def train(data: Path, out: Path) -> dict:
    """Fit the logistic regression on ``data``; cross-validated by object (5 folds)."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.metrics import roc_auc_score
    from sklearn.model_selection import GroupKFold, cross_val_predict
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    with data.open() as f:
        rows = list(csv.DictReader(f))
    x = np.array([[float(r[name]) for name in FEATURES] for r in rows])
    y = np.array([int(r["held"]) for r in rows])
    groups = np.array([r["object_id"] for r in rows])
    model = make_pipeline(StandardScaler(), LogisticRegression(C=1.0, max_iter=1000))
    p = cross_val_predict(model, x, y, groups=groups, cv=GroupKFold(5), method="predict_proba")
    # how often the top grasp by the model holds, against the planner's order (rank 0)
    top_model, top_plan, objects = 0, 0, sorted(set(groups))
    for o in objects:
        sel = np.flatnonzero(groups == o)
        top_model += y[sel[np.argmax(p[sel, 1])]]
        top_plan += y[sel[0]]
    model.fit(x, y)
    scaler, logistic = model[0], model[1]
    result = {
        "features": list(FEATURES),
        "mean": scaler.mean_.tolist(), "scale": scaler.scale_.tolist(),
        "coef": logistic.coef_[0].tolist(), "intercept": float(logistic.intercept_[0]),
        "data": str(data.name), "grasps": len(y), "objects": len(objects), "held": int(y.sum()),
        "cv_auc": round(float(roc_auc_score(y, p[:, 1])), 4),
        "cv_top_grasp_held": {"model": int(top_model), "planner_order": int(top_plan),
                              "objects": len(objects)},
    }
    out.write_text(json.dumps(result, indent=1) + "\n")
    return result


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        prog="python -m grasp.lift_model", description=__doc__.split(
        "\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        help="lift-test grasps on training-split objects (CSV)",
    )
    c.add_argument("--objects", type=int, default=200, help="training objects (default 200)")
    c.add_argument("--seed", type=int, default=0, help="seed of the objects and poses (default 0)")
    c.add_argument("--workers", type=int, default=2, help="processes (default 2)")
    c.add_argument("--out", type=Path, default=DATA_PATH, help=f"CSV (default {DATA_PATH.name})")
    t = sub.add_parser("train",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        help="fit the model on the CSV, write its JSON",
    )
    t.add_argument("--data", type=Path, default=DATA_PATH, help=f"default {DATA_PATH.name}")
    t.add_argument("--out", type=Path, default=MODEL_PATH, help=f"default {MODEL_PATH.name}")
    args = parser.parse_args(argv)
    if args.command == "collect":
        if args.objects < 1 or args.workers < 1:
            parser.error("--objects and --workers must be at least 1")
        collect(args.objects, args.seed, args.out, args.workers)
    else:
        result = train(args.data, args.out)
        print(json.dumps({k: v for k, v in result.items() if k not in ("mean", "scale", "coef")}))


if __name__ == "__main__":
    main()
