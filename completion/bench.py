"""Per-view streaming latency and carried-state size against the number of views seen.

``python -m completion.bench`` prints JSON::

    {"models": {"<name>": {"latency_ms": {"1": ..., "10": ..., "100": ..., "1000": ...},
                           "state_bytes": {"1": ..., ...}, "params": ..., "weights": ...}},
     "device": "cpu", "threads": 1, ...}

``latency_ms[L]`` is the median wall time of one ``model.step`` (batch 1, CPU, inference mode)
taken from the state after L earlier views, ``cpu_ms[L]`` the median CPU time of this thread for
the same steps (robust to other processes on a shared machine when ``--threads 1``);
``input_ms`` is what a depth image costs before the model, with :mod:`completion.depth`'s
cleaning and without (:func:`bench_input`). ``state_bytes[L]`` is the length of
``state_to_bytes(state)`` after L views, i.e. what a service stores per session. Between
checkpoints the stream is advanced without decoding (``model.advance``), and only ``--repeats``
steps are timed at each checkpoint (each from the same state, the checkpoints in turn), so 1000
views take seconds.
Shipped weights from ``completion/weights/<name>.pt`` are used when present
(``"weights": "shipped"``), otherwise a freshly initialised model of the default config
(``"weights": "fresh"``); latency and state size do not depend on the weights' values.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Sequence
from typing import Any, Literal

import torch

from completion.cli import HelpWithDefaults, name_list
from completion.config import DEFAULT_CONFIGS, default_config
from completion.model import (
    WEIGHTS_DIR,
    CompletionModel,
    build_model,
    load_model,
    state_nbytes,
    state_to_bytes,
)

DEFAULT_MODELS = ("mvp", "mvt", "lstm", "single_view")
DEFAULT_VIEWS = (1, 10, 100, 1000)
DEFAULT_REPEATS = 15
WARMUP_STEPS = 2
INPUT_OCCUPANCY = 0.02
"""Fraction of occupied input voxels in the synthetic frames (timing does not depend on it)."""


def resolve_model(name: str) -> tuple[CompletionModel, Literal["shipped", "fresh"]]:
    """Shipped weights for ``name`` if present, else a fresh model of its default config."""
    if (WEIGHTS_DIR / f"{name}.pt").is_file():
        return load_model(name), "shipped"
    return build_model(default_config(name)), "fresh"


def bench_model(
    model: CompletionModel, *, views: Sequence[int], repeats: int = DEFAULT_REPEATS, seed: int = 0
) -> dict[str, Any]:
    """Time one streaming step after each L in ``views`` and record the state size.

    Returns {"latency_ms": {str(L): float}, "cpu_ms": {str(L): float}, "state_bytes": {str(L): int},
    "state_tensor_bytes": {str(L): int}, "params": int}.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    checkpoints = sorted(set(views))
    if not checkpoints or checkpoints[0] < 0:
        raise ValueError(f"views must be non-negative view counts, got {list(views)}")
    g = model.config.grid_size
    generator = torch.Generator().manual_seed(seed)
    device = next(model.parameters()).device
    frames = (torch.rand(4, 1, g, g, g, generator=generator) < INPUT_OCCUPANCY).float().to(device)
    model.eval()
    latency: dict[str, float] = {}
    cpu: dict[str, float] = {}
    sizes: dict[str, int] = {}
    tensor_sizes: dict[str, int] = {}
    with torch.inference_mode():
        state = model.init_state(1)
        for i in range(WARMUP_STEPS):
            model.step(state, frames[i % len(frames)])
        seen, states = 0, {}
        for count in checkpoints:
            while seen < count:
                state = model.advance(state, frames[seen % len(frames)])
                seen += 1
            states[count] = state
            sizes[str(count)] = len(state_to_bytes(state))
            tensor_sizes[str(count)] = state_nbytes(state)
        # round robin over the checkpoints, so that a slow spell of a shared machine falls on
        # every L alike and the ratios between them stay meaningful
        times = {count: [] for count in checkpoints}
        cpu_times = {count: [] for count in checkpoints}
        for r in range(repeats):
            for count in checkpoints:
                frame = frames[(count + r) % len(frames)]
                start, cpu_start = time.perf_counter(), time.thread_time()
                model.step(states[count], frame)
                times[count].append(time.perf_counter() - start)
                cpu_times[count].append(time.thread_time() - cpu_start)
        for count in checkpoints:
            latency[str(count)] = round(1000.0 * statistics.median(times[count]), 3)
            cpu[str(count)] = round(1000.0 * statistics.median(cpu_times[count]), 3)
    return {
        "latency_ms": latency,
        "cpu_ms": cpu,
        "state_bytes": sizes,
        "state_tensor_bytes": tensor_sizes,
        "params": model.n_params(),
    }


def bench_input(repeats: int = DEFAULT_REPEATS) -> dict[str, Any]:
    """What a depth image costs before the model (:func:`completion.grid.depth_to_points` and
    :func:`completion.grid.fit_seen`), with the cleaning of :mod:`completion.depth` and without:
    median milliseconds over ``repeats`` on a tabletop view through the sensor model (320×240,
    and the same view at 640×480, every pixel repeated 2×2, intrinsics scaled)."""
    import numpy as np

    from completion import grid
    from completion.scenes import make_sequence

    seq = make_sequence("tabletop", "test", 0, 0, views=2, keep_depth=True)
    k = seq.meta["intrinsics"]
    small = grid.Intrinsics(**k)
    large = grid.Intrinsics(2 * k["fx"], 2 * k["fy"], 2 * k["cx"] + 0.5, 2 * k["cy"] + 0.5,
                            2 * k["width"], 2 * k["height"])
    images = {
        "320x240": (seq.depth[0], seq.mask[0] >= 0, small),
        "640x480": (np.repeat(np.repeat(seq.depth[0], 2, 0), 2, 1),
                    np.repeat(np.repeat(seq.mask[0] >= 0, 2, 0), 2, 1), large),
    }
    out: dict[str, Any] = {}
    for name, (depth, mask, intrinsics) in images.items():
        times: dict[str, list[float]] = {"raw": [], "cleaned": []}
        for _ in range(repeats):
            for key, cleaning in (("raw", None), ("cleaned", grid.DEPTH_FILTER)):
                start = time.perf_counter()
                points = grid.depth_to_points(depth, intrinsics, mask, cleaning=cleaning)
                grid.fit_seen(points, cleaning=cleaning)
                times[key].append(time.perf_counter() - start)
        out[name] = {key: round(1000.0 * statistics.median(v), 2) for key, v in times.items()}
        out[name]["points"] = len(grid.depth_to_points(depth, intrinsics, mask))
    return out


def run_bench(
    models: Sequence[str] = DEFAULT_MODELS,
    *,
    views: Sequence[int] = DEFAULT_VIEWS,
    repeats: int = DEFAULT_REPEATS,
    threads: int = 1,
) -> dict[str, Any]:
    """Benchmark the named models (shipped weights or default configs) on the CPU."""
    unknown = [name for name in models if name not in DEFAULT_CONFIGS]
    if unknown:
        raise ValueError(f"unknown models {unknown}; expected names from {sorted(DEFAULT_CONFIGS)}")
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        results: dict[str, Any] = {}
        for name in models:
            model, source = resolve_model(name)
            entry = bench_model(model, views=views, repeats=repeats)
            results[name] = {"kind": model.config.kind, "weights": source, **entry}
    finally:
        torch.set_num_threads(previous)
    return {
        "models": results,
        "input_ms": bench_input(repeats),
        "device": "cpu",
        "threads": threads,
        "batch": 1,
        "repeats": repeats,
        "torch": torch.__version__,
    }


def _int_list(text: str) -> list[int]:
    try:
        return [int(part) for part in text.split(",") if part.strip()]
    except ValueError as error:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got {text!r}"
        ) from error


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(formatter_class=HelpWithDefaults,
        prog="python -m completion.bench",
        description="Streaming latency and state size per view count (JSON on stdout).",
    )
    parser.add_argument(
        "--models",
        type=name_list(tuple(sorted(DEFAULT_CONFIGS)), "models"),
        default=list(DEFAULT_MODELS),
        help=f"comma-separated names from {sorted(DEFAULT_CONFIGS)} (default: %(default)s)",
    )
    parser.add_argument(
        "--views",
        type=_int_list,
        default=list(DEFAULT_VIEWS),
        help="comma-separated view counts L (default: 1,10,100,1000)",
    )
    parser.add_argument(
        "--repeats", type=int, default=DEFAULT_REPEATS, help="timed steps per L (median)"
    )
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = parser.parse_args(argv)
    try:
        report = run_bench(
            args.models, views=args.views, repeats=args.repeats, threads=args.threads
        )
    except ValueError as error:
        parser.error(str(error))
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
