"""What each part of the sensor model costs one model: ``python -m grasp.evaluate.sensor_parts``.

The same test sequences (seed 0) rendered noiseless, through the whole
:class:`completion.depth_camera.SensorModel`, and with one part of it switched off at a time (flying
pixels; every edge effect, holes and flying pixels; everything but the Gaussian axial noise).
Per part and condition: the model's mean Jaccard, its difference from the noiseless sequences
and the mean voxel side of the grids, as a markdown table. ``--no-cleaning`` feeds the raw depth
(every return, the plain bounding box) instead of :mod:`completion.depth`'s cleaned input, to
see what the cleaning buys (a model trained on the other input is then off its training data).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import numpy as np

from completion.cli import HelpWithDefaults
from completion.depth_camera import SensorModel

#: name -> the sensor (None: noiseless).
PARTS: dict[str, SensorModel | None] = {
    "off": None,
    "all of it": SensorModel(),
    "no flying pixels": SensorModel(edge_flying=0.0),
    "no edge effects (holes, flying)": SensorModel(edge_hole=0.0, edge_flying=0.0),
    "Gaussian σ(z) alone": SensorModel(edge_hole=0.0, edge_flying=0.0, subpixel=0, dropout=0.0),
}
_MODEL = None


def _load(weights: str) -> None:
    global _MODEL
    import torch

    from completion.model import load_model

    torch.set_num_threads(1)
    _MODEL = load_model(weights).eval()


def _one(job: tuple[str, str, int, bool]) -> tuple[str, str, float, float]:
    import torch

    from completion import grid
    from completion.depth import DEPTH_FILTER
    from completion.scenes import make_sequence

    part, condition, index, clean = job
    sensor = PARTS[part]
    seq = make_sequence(condition, "test", index, 0, noise=sensor is not None,
                        sensor=sensor or SensorModel(), cleaning=DEPTH_FILTER if clean else None)
    with torch.no_grad():
        p = torch.sigmoid(_MODEL(torch.from_numpy(seq.inputs[None].astype(np.float32))))[0]
    jaccard = float(grid.jaccard(p.numpy() >= _MODEL.threshold, seq.targets).mean())
    side = float(np.mean([grid.pitch_of(t) for t in seq.grid_to_camera]))
    return part, condition, jaccard, side


def measure(weights: str, conditions: Sequence[str], count: int, clean: bool,
            workers: int) -> dict:
    """part -> condition -> {"jaccard", "difference", "voxel_mm"} (means over ``count``)."""
    from multiprocessing import Pool

    jobs = [(part, c, i, clean) for part in PARTS for c in conditions
            for i in range(count)]
    with Pool(workers, initializer=_load, initargs=(weights,)) as pool:
        done = pool.map(_one, jobs, chunksize=1)
    out: dict = {}
    for part in PARTS:
        out[part] = {}
        for c in conditions:
            mine = [(j, s) for p, cc, j, s in done if p == part and cc == c]
            out[part][c] = {"jaccard": round(float(np.mean([j for j, _ in mine])), 4),
                            "voxel_mm": round(1000 * float(np.mean([s for _, s in mine])), 2)}
    for part in PARTS:
        for c in conditions:
            out[part][c]["difference"] = round(out[part][c]["jaccard"] - out["off"][c]["jaccard"],
                                               4)
    return out


def markdown(table: dict, conditions: Sequence[str]) -> str:
    head = "| sensor | " + " | ".join(f"{c} Jaccard | minus off | voxel side" for c in conditions)
    lines = [head + " |", "|---|" + "---|---|---|" * len(conditions)]
    for part, cells in table.items():
        row = [f"{cells[c]['jaccard']:.3f} | {cells[c]['difference']:+.3f} | "
               f"{cells[c]['voxel_mm']:.2f} mm" for c in conditions]
        lines.append(f"| {part} | " + " | ".join(row) + " |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m grasp.evaluate.sensor_parts",
                                     description=__doc__.split("\n\n")[0],
                                     formatter_class=HelpWithDefaults)
    parser.add_argument("--weights", default="completion/weights/mvp.pt",
                        help="the model's checkpoint (default completion/weights/mvp.pt)")
    parser.add_argument("--conditions", default="camera_pan,tabletop",
                        help="comma list (default camera_pan,tabletop)")
    parser.add_argument("--count", type=int, default=6,
                        help="test sequences per condition (default 6)")
    parser.add_argument("--no-cleaning", action="store_true",
                        help="raw depth and the plain box instead of the cleaned input "
                             "(default: cleaned)")
    parser.add_argument("--workers", type=int, default=2, help="processes (default 2)")
    args = parser.parse_args(argv)
    from completion.scenes import CONDITIONS

    conditions = [c.strip() for c in args.conditions.split(",") if c.strip()]
    unknown = [c for c in conditions if c not in CONDITIONS]
    if unknown or not conditions:
        parser.error(f"--conditions must name some of {', '.join(CONDITIONS)}; got {unknown}")
    if args.count < 1 or args.workers < 1:
        parser.error("--count and --workers must be at least 1")
    table = measure(args.weights, conditions, args.count, not args.no_cleaning, args.workers)
    print(markdown(table, conditions))


if __name__ == "__main__":
    main()

