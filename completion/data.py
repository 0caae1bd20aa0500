"""Shards of simulated sequences, and the ``python -m completion.data`` command.

Shard format (docs/design.md §4): one compressed ``.npz`` per sequence, named
``<condition>_<split>_s<seed>_<index:05d>.npz``, holding

- ``inputs`` (L, 40, 40, 40) bool and ``targets`` (L, 40, 40, 40) bool,
- ``grid_to_camera`` (L, 4, 4) float64 and ``camera_to_world`` (L, 4, 4) float64,
- ``depth`` (L, H, W) float32 and ``mask`` (L, H, W) int16, only with ``--keep-depth``,
- ``meta``: a JSON string (condition, split, index, seed, object ids, intrinsics, object poses,
  the scale each object mesh was given before it was posed (``object_scale``; shards written
  before it lack it: 1), visible points per object per view, curtain positions).

Examples::

    python -m completion.data generate --condition camera_pan --split train --count 100 \\
        --seed 0 --out data/train --workers 2
    python -m completion.data show data/train/camera_pan_train_s0_00000.npz --out view.png
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import time
import zipfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from completion.cli import DefaultsAndRawDescription, HelpWithDefaults, integer_at_least, name_list
from completion.scenes import CONDITIONS, VIEWS, Sequence, make_sequence

SHARD_KEYS = ("inputs", "targets", "grid_to_camera", "camera_to_world")


def shard_name(condition: str, split: str, seed: int, index: int) -> str:
    return f"{condition}_{split}_s{seed}_{index:05d}.npz"


def sequence_bytes(seq: Sequence) -> bytes:
    """One sequence as the bytes of a compressed shard."""
    arrays = {k: getattr(seq, k) for k in SHARD_KEYS}
    if seq.depth is not None:
        arrays["depth"] = seq.depth
        arrays["mask"] = seq.mask
    buffer = io.BytesIO()
    np.savez_compressed(buffer, meta=np.array(json.dumps(seq.meta)), **arrays)
    return buffer.getvalue()


def write_shard(data: bytes, path: str | Path) -> Path:
    """Write shard bytes; never leaves a half-written shard behind. Returns the path."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp.npz")
    tmp.write_bytes(data)
    tmp.replace(path)
    return path


def save_sequence(seq: Sequence, path: str | Path) -> Path:
    """Write one sequence as a compressed shard; returns the path."""
    return write_shard(sequence_bytes(seq), path)


def load_sequence(path: str | Path) -> Sequence:
    """Read a shard written by :func:`save_sequence`, checking its keys and shapes."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, EOFError, ValueError, zipfile.BadZipFile) as exc:
        raise ValueError(f"cannot read shard {path}: {exc}") from exc
    missing = [k for k in (*SHARD_KEYS, "meta") if k not in arrays]
    if missing:
        raise ValueError(f"{path} is not a sequence shard: missing {missing}")
    n = len(arrays["inputs"])
    for k, shape in (
        ("inputs", (40, 40, 40)),
        ("targets", (40, 40, 40)),
        ("grid_to_camera", (4, 4)),
        ("camera_to_world", (4, 4)),
    ):
        if arrays[k].shape != (n, *shape):
            raise ValueError(f"{path}: {k} has shape {arrays[k].shape}, expected {(n, *shape)}")
    return Sequence(
        inputs=arrays["inputs"].astype(bool),
        targets=arrays["targets"].astype(bool),
        grid_to_camera=arrays["grid_to_camera"],
        camera_to_world=arrays["camera_to_world"],
        meta=json.loads(str(arrays["meta"])),
        depth=arrays.get("depth"),
        mask=arrays.get("mask"),
    )


_WORKER_RENDERER = None


def _render(job: tuple) -> Sequence:
    """Worker: render one sequence (one pybullet client per process)."""
    global _WORKER_RENDERER
    from completion.depth_camera import Renderer

    condition, split, index, seed, _, views, noise, keep_depth = job
    if _WORKER_RENDERER is None:
        _WORKER_RENDERER = Renderer()
    return make_sequence(
        condition,
        split,
        index,
        seed,
        views=views,
        renderer=_WORKER_RENDERER,
        noise=noise,
        keep_depth=keep_depth,
    )


def _job_path(job: tuple) -> Path:
    condition, split, index, seed, out = job[:5]
    return Path(out) / shard_name(condition, split, seed, index)


def _generate_one(job: tuple) -> str:
    """Worker: render one sequence and write its shard."""
    return str(save_sequence(_render(job), _job_path(job)))


def _shard_of(job: tuple) -> bytes:
    """Ray worker: render one sequence and send its shard back (the nodes share no disk)."""
    return sequence_bytes(_render(job))


def generate(
    conditions: list[str],
    split: str,
    count: int,
    *,
    seed: int = 0,
    out: str | Path,
    workers: int = 1,
    views: int = VIEWS,
    noise: bool | None = None,
    keep_depth: bool = False,
    progress: bool = True,
    start: int = 0,
    ray: bool = False,
) -> list[Path]:
    """Generate ``count`` sequences per condition into ``out``; existing shards are kept.

    ``ray``: render on ``workers`` Ray actors (:mod:`completion.cluster`, a local runtime or
    ``RAY_ADDRESS``) and write the shards here; the same shards as the process pool."""
    from tqdm import tqdm

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    jobs, paths = [], []
    for condition in conditions:
        for index in range(start, start + count):
            path = out / shard_name(condition, split, seed, index)
            paths.append(path)
            if not path.exists():
                jobs.append((condition, split, index, seed, str(out), views, noise, keep_depth))
    bar = tqdm(total=len(jobs), desc=f"generate {split}", unit="seq", disable=not progress)
    if ray:
        from completion.cluster import ray_map

        for job, data in zip(jobs, ray_map(_shard_of, jobs, workers=workers), strict=True):
            write_shard(data, _job_path(job))
            bar.update()
    elif workers <= 1:
        for job in jobs:
            _generate_one(job)
            bar.update()
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            for _ in pool.map(_generate_one, jobs, chunksize=4):
                bar.update()
    bar.close()
    return paths


def show(path: str | Path, out: str | Path) -> Path:
    """Draw a sequence: for each view, max projections along the camera z axis of the input and
    target grids (rows), so a person can see what the model gets and should produce."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seq = load_sequence(path)
    n = len(seq)
    fig, axes = plt.subplots(2, n, figsize=(1.4 * n, 3.2), squeeze=False)
    for t in range(n):
        for row, (name, grid) in enumerate((("input", seq.inputs[t]), ("target", seq.targets[t]))):
            ax = axes[row, t]
            # Depth-coded projection: nearer voxels (small k) brighter; image rows are camera y.
            k = np.arange(grid.shape[2])[None, None, :]
            proj = np.where(grid, 40 - k, 0).max(axis=2).T
            ax.imshow(proj, cmap="viridis", vmin=0, vmax=40, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if t == 0:
                ax.set_ylabel(name)
            if row == 0:
                ax.set_title(f"view {t}", fontsize=8)
    meta = seq.meta
    fig.suptitle(f"{meta.get('condition')} · {', '.join(meta.get('object_ids', []))}", fontsize=9)
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def parse_conditions(text: str) -> list[str]:
    """CLI type: 'all' or a comma list of conditions, in any case (argparse error otherwise)."""
    return list(name_list(CONDITIONS, "conditions")(text))


_positive = integer_at_least(1)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m completion.data",
        description=__doc__,
        formatter_class=DefaultsAndRawDescription,
    )
    sub = parser.add_subparsers(dest="command", required=True)
    g = sub.add_parser("generate",
        formatter_class=HelpWithDefaults,
        help="render sequences and write shards",
    )
    g.add_argument(
        "--condition",
        type=parse_conditions,
        default=list(CONDITIONS),
        help="a condition, a comma list, or 'all' (default all)",
    )
    g.add_argument("--split", choices=("train", "val", "test"), required=True)
    g.add_argument("--count", type=_positive, required=True, help="sequences per condition")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--out", type=Path, required=True)
    g.add_argument("--workers", type=_positive, default=1,
                   help="processes (with --ray: Ray actors, one CPU each)")
    g.add_argument("--ray", action="store_true",
                   help="render on Ray: the cluster at RAY_ADDRESS, else a local runtime "
                   "(pip install -e '.[cluster]')")
    g.add_argument("--views", type=_positive, default=VIEWS)
    g.add_argument("--noise", choices=("auto", "on", "off"), default="auto",
                   help="the sensor model (completion.depth_camera.SensorModel): auto = on for "
                   "tabletop only, on = every condition, off = none")
    g.add_argument("--keep-depth", action="store_true", help="store depth and mask images too")
    s = sub.add_parser("show",
        formatter_class=HelpWithDefaults,
        help="draw a shard's inputs and targets to a PNG",
    )
    s.add_argument("file", type=Path)
    s.add_argument("--out", type=Path, default=Path("view.png"))
    args = parser.parse_args(argv)
    if args.command == "generate":
        tic = time.perf_counter()
        paths = generate(
            args.condition,
            args.split,
            args.count,
            seed=args.seed,
            out=args.out,
            workers=args.workers,
            views=args.views,
            noise={"auto": None, "on": True, "off": False}[args.noise],
            keep_depth=args.keep_depth,
            ray=args.ray,
        )
        dt = time.perf_counter() - tic
        size = sum(p.stat().st_size for p in paths) / max(len(paths), 1)
        print(f"{len(paths)} sequences in {args.out} ({dt:.1f} s, mean shard {size / 1e3:.0f} kB)")
    else:
        if not args.file.is_file():
            parser.error(f"no such shard: {args.file}")
        print(show(args.file, args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
