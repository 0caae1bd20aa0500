"""The lift model's data and training (:mod:`grasp.ranking.lift_model` applies it).

``python -m grasp.evaluate.lift_training collect`` rests training-split objects (never the
benchmark's, which are held out) on a table in a stable pose, plans on the true mesh with the table,
and
lift-tests every force-closure grasp the planner ranks (guarded execution, as the benchmark):
``grasp/ranking/lift_model_data.csv``, one row per grasp. ``python -m grasp.evaluate.lift_training
train`` fits the logistic regression (scikit-learn) and writes ``grasp/ranking/lift_model.json``
with its cross-validated figures (grouped by object).
"""

from __future__ import annotations

import argparse
import csv
import json
import time
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from grasp.ranking.lift_model import DATA_PATH, FEATURES, MODEL_PATH, features
from grasp_client.wire import SupportPlane


def _collect_one(job: tuple[int, str, int]) -> list[dict]:
    from completion.objects import load_object
    from completion.scenes import stable_pose
    from grasp.physics.lift import lift_test
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
        lifted = lift_test(world, grasp, seed=index, support_plane=table, approach="guarded")
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
        prog="python -m grasp.evaluate.lift_training", description=__doc__.split(
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
