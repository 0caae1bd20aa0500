"""Fan work out over a Ray cluster (``--ray``): data generation and evaluation.

``ray_map(fn, items, workers=N)`` runs ``fn`` on every item in ``N`` Ray actors (one CPU each),
each set up once by ``initializer(*initargs)`` like a process pool's worker, and yields the
results in the order of ``items``: the same seeds give the same shards and tables as the local
process pool. Ray runs on the cluster named by ``RAY_ADDRESS`` (``ray start --head`` on one
machine, ``ray start --address …`` on the others), else on a local runtime started here. Every
node needs this package installed (``pip install -e '.[cluster]'``). Ray is an optional extra;
nothing imports it unless ``--ray`` is given.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Iterable, Iterator
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")


def _ray():
    try:
        import ray
    except ImportError as exc:
        raise RuntimeError(
            "--ray needs Ray: pip install -e '.[cluster]' (the 'cluster' extra)"
        ) from exc
    return ray


def init(workers: int) -> None:
    """Connect to ``RAY_ADDRESS``, or start a local runtime with ``workers`` CPUs."""
    ray = _ray()
    if ray.is_initialized():
        return
    quiet = dict(include_dashboard=False, log_to_driver=False, logging_level="warning")
    if os.environ.get("RAY_ADDRESS"):
        ray.init(**quiet)  # an existing cluster: its own CPUs
    else:
        ray.init(num_cpus=workers, **quiet)


class _Worker:
    """A Ray actor: runs the initializer once, then one function call per item."""

    def __init__(self, initializer: Callable[..., None] | None, initargs: tuple) -> None:
        if initializer is not None:
            initializer(*initargs)

    def run(self, fn: Callable[[Any], Any], item: Any) -> Any:
        return fn(item)


@functools.cache
def _remote_worker():
    """The actor class, made once per process: Ray exports a class to the cluster's store once
    per job, where a class made per call is exported again by every call (a store write that
    once stalled a CI run on a single-node runtime)."""
    return _ray().remote(num_cpus=1)(_Worker)


def ray_map(
    fn: Callable[[T], R],
    items: Iterable[T],
    *,
    workers: int,
    initializer: Callable[..., None] | None = None,
    initargs: tuple = (),
) -> Iterator[R]:
    """``fn(item)`` for every item on ``workers`` Ray actors, yielded in the order of ``items``."""
    ray = _ray()
    from ray.util import ActorPool

    init(workers)
    actors = [_remote_worker().remote(initializer, initargs) for _ in range(workers)]
    try:
        yield from ActorPool(actors).map(lambda a, item: a.run.remote(fn, item), list(items))
    finally:
        for a in actors:
            ray.kill(a)
