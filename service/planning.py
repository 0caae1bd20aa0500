"""Grasp planning off the event loop: in worker processes by default, or in threads.

Planning is seconds of Python per request. In a process pool it neither holds the GIL that the
event loop and the model steps need nor takes the server down if it crashes, and it runs at a
lower CPU priority than the model steps of ``POST /views``. ``GRASP_PLANNING_PROCESSES=false``
runs it in threads instead (what the in-process tests use). This module does not import torch,
so the worker processes stay small.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from functools import partial

import anyio.to_thread
import numpy as np
from anyio import CapacityLimiter

log = logging.getLogger(__name__)

#: Planner processes run at this lower CPU priority, so that model steps (POST /views) come first.
PLANNER_NICENESS = 5


def plan_grasps(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    n_candidates: int,
    seed: int,
    top_k: int,
    support_plane=None,
) -> tuple[list, float]:
    """``grasp.planner.plan`` on the mesh (vertices (v, 3), faces (f, 3)); also its seconds.

    ``support_plane``: a ``grasp.planner.SupportPlane`` in the mesh's frame, or None."""
    import trimesh

    from grasp.planner import plan

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    start = time.perf_counter()
    results = plan(
        mesh, n_candidates=n_candidates, seed=seed, top_k=top_k, support_plane=support_plane
    )
    return results, time.perf_counter() - start


def _import_planner() -> None:
    import grasp.planner  # noqa: F401


class Planner:
    """Runs :func:`plan_grasps`, at most ``workers`` at once, in processes or threads."""

    def __init__(self, workers: int, *, processes: bool) -> None:
        self.workers = workers
        self.processes = processes
        self._limiter = CapacityLimiter(workers)
        self._pool: ProcessPoolExecutor | None = None

    def _executor(self) -> ProcessPoolExecutor:
        if self._pool is None:
            # spawn: the server has torch's thread pools running, which fork does not survive.
            context = multiprocessing.get_context("spawn")
            self._pool = ProcessPoolExecutor(
                self.workers, mp_context=context, initializer=os.nice, initargs=(PLANNER_NICENESS,)
            )
        return self._pool

    async def plan(
        self,
        vertices: np.ndarray,
        faces: np.ndarray,
        *,
        n_candidates: int,
        seed: int,
        top_k: int,
        support_plane=None,
    ) -> tuple[list, float]:
        call = partial(
            plan_grasps,
            vertices,
            faces,
            n_candidates=n_candidates,
            seed=seed,
            top_k=top_k,
            support_plane=support_plane,
        )
        if not self.processes:
            return await anyio.to_thread.run_sync(call, limiter=self._limiter)
        pool = self._executor()
        try:
            return await asyncio.get_running_loop().run_in_executor(pool, call)
        except BrokenProcessPool:
            log.error("a planner process died; starting a new pool")
            if self._pool is pool:
                self._pool = None
                pool.shutdown(wait=False, cancel_futures=True)
            raise

    def warm_up(self) -> None:
        """Start the worker processes and import the planner there, without waiting for it."""
        if self.processes:
            for _ in range(self.workers):
                self._executor().submit(_import_planner)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
