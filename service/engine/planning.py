"""Grasp planning off the event loop: in worker processes by default, or in threads.

Planning is seconds of Python per request. In a process pool it neither holds the GIL that the
event loop and the model steps need nor takes the server down if it crashes, and it runs at a
lower CPU priority than the model steps of ``POST /views``. ``GRASP_PLANNING_PROCESSES=false``
runs it in threads instead (what the in-process tests use). This module does not import torch,
so the worker processes stay small.

Requests beyond the workers wait in a bounded queue (``GRASP_PLANNING_QUEUE``; more get 503 at
once rather than piling up; one client at most ``GRASP_CLIENT_PLANS`` of them, so that it cannot
fill the queue for the others). A free worker goes to the waiting clients in turn
(:class:`FairSlots`: round-robin over clients, first come first served within one), and one
client's verification runs on at most ``GRASP_CLIENT_TRIALS`` workers at once (with several
tokens, all but one), so that another client's plan finds a worker within a plan's time. A request
whose client has gone while it waited is dropped before it reaches a worker, and a plan is kept
(``GRASP_PLAN_CACHE`` plans, least recently used out, each client's its own) so that asking
again about an unchanged mesh with the same options costs nothing: the inspector page,
``scene.glb`` and a robot polling ``GET /grasp`` between views all hit it.

With ``verify=N`` (:mod:`grasp.physics.verify`) the plan ranks every autograsped grasp, a second
worker computes the completion's convex pieces meanwhile (:func:`decompose`, into the disk cache the
lift test reads), and then each tried grasp's trials run at once, each in a worker slot of its own
taken in turn with other requests' plans (:func:`lift_trial`), so that one request's verification
does not hold other sessions back by more than a grasp's trials.
"""

from __future__ import annotations

import asyncio
import functools
import hashlib
import logging
import multiprocessing
import time
from collections import OrderedDict, deque
from collections.abc import Awaitable, Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import asynccontextmanager
from dataclasses import dataclass
from functools import partial

import anyio.to_thread
import numpy as np

from grasp.defaults import AUTOGRASP_BUDGET, HOLD_THRESHOLD
from grasp_client.wire import SupportPlane
from service.intake import workers

log = logging.getLogger(__name__)

#: Planner processes run at this lower CPU priority, so that model steps (POST /views) come first.
PLANNER_NICENESS = 5


@dataclass(frozen=True, eq=False)
class PlanRequest:
    """One plan, built once where it is asked for (``GET /grasp``) and passed whole to a worker:
    the mesh (vertices (v, 3), faces (f, 3), the completion's camera frame), the candidates and
    how many are autograsped (``budget``, :data:`grasp.defaults.AUTOGRASP_BUDGET` by default),
    the seed, how many grasps come back, the table (a :class:`grasp_client.wire.SupportPlane` in
    the mesh's frame, or None), the obstacles (voxel centres (k, 3) in the mesh's frame, of the
    session's pitch :data:`completion.grid.OBSTACLE_PITCH_M`, or None) and how many of the best
    grasps to lift-test before answering (:mod:`grasp.physics.verify`), and the hold probability
    under which a force-closure grasp on the table is refused (``min_hold``)."""

    vertices: np.ndarray
    faces: np.ndarray
    n_candidates: int
    seed: int
    top_k: int
    budget: int = AUTOGRASP_BUDGET
    support_plane: SupportPlane | None = None
    obstacles: np.ndarray | None = None
    verify: int = 0
    min_hold: float = HOLD_THRESHOLD

    @functools.cached_property
    def key(self) -> str:
        """The plan's identity (the cache's key): the mesh's bytes, the obstacles' and every
        option."""
        digest = hashlib.sha1()
        digest.update(np.ascontiguousarray(self.vertices, dtype="<f8").tobytes())
        digest.update(np.ascontiguousarray(self.faces, dtype="<i8").tobytes())
        if self.obstacles is not None and len(self.obstacles):
            digest.update(b"obstacles" + np.ascontiguousarray(self.obstacles, "<f8").tobytes())
        plane = None if self.support_plane is None else (
            *np.round(self.support_plane.normal, 12).tolist(),
            round(self.support_plane.offset, 12))
        options = (self.n_candidates, self.seed, self.top_k, self.budget, self.verify, plane,
                   self.min_hold)
        digest.update(repr(options).encode())
        return digest.hexdigest()


def plan_grasps(request: PlanRequest) -> tuple[list, float]:
    """``grasp.planner.plan`` of the request (every autograsped grasp, ranked, when it is to be
    verified: the verification picks from them); also its seconds."""
    import trimesh

    from grasp.planner import plan
    from grasp.search.obstacles import Obstacles

    r = request
    mesh = trimesh.Trimesh(r.vertices, r.faces, process=False)
    start = time.perf_counter()
    obstacles = Obstacles(r.obstacles) if r.obstacles is not None and len(r.obstacles) else None
    results = plan(mesh, n_candidates=r.n_candidates, seed=r.seed,
                   top_k=None if r.verify else r.top_k, support_plane=r.support_plane,
                   budget=r.budget, obstacles=obstacles, min_hold=r.min_hold)
    return results, time.perf_counter() - start


def lift_trial(vertices: np.ndarray, faces: np.ndarray, grasp, support_plane, trial):
    """One verification trial (:func:`grasp.physics.verify.run_trial`) of ``grasp`` on the mesh."""
    import trimesh

    from grasp.physics.verify import run_trial

    return run_trial(trimesh.Trimesh(vertices, faces, process=False), grasp, support_plane, trial)


def decompose(vertices: np.ndarray, faces: np.ndarray) -> None:
    """The mesh's convex pieces for the lift test, computed into the shared disk cache
    (:func:`grasp.physics.body.convex_decomposition`) while another worker plans."""
    import trimesh

    from grasp.physics.body import convex_decomposition

    convex_decomposition(trimesh.Trimesh(vertices, faces, process=False))


def _import_planner() -> None:
    import grasp.planner  # noqa: F401


class PlannerBusy(RuntimeError):
    """More grasp plans are waiting than the queue holds, or than one client may have."""


class FairSlots:
    """``n`` worker slots, taken by clients (any hashable name, "" for everyone without tokens):
    a freed slot goes to the next client in turn that is waiting (round-robin), and within a client
    to its longest waiting call. One client's many calls therefore delay another's by at most the
    calls already running, not by its whole queue."""

    def __init__(self, n: int) -> None:
        self.free = n
        self._waiting: OrderedDict[str, deque[asyncio.Future]] = OrderedDict()

    @asynccontextmanager
    async def take(self, client: str):
        if self.free and not self._waiting:
            self.free -= 1
        else:
            turn = asyncio.get_running_loop().create_future()
            self._waiting.setdefault(client, deque()).append(turn)
            try:
                await turn
            except asyncio.CancelledError:
                if turn.done() and not turn.cancelled():
                    self._hand_on()  # given the slot as it was cancelled: pass it on
                else:
                    self._drop(client, turn)
                raise
        try:
            yield
        finally:
            self._hand_on()

    def _hand_on(self) -> None:
        """A slot is free: to the first waiting client, which then goes to the back."""
        while self._waiting:
            client, turns = next(iter(self._waiting.items()))
            turn = turns.popleft()
            if turns:
                self._waiting.move_to_end(client)
            else:
                del self._waiting[client]
            if not turn.done():
                turn.set_result(None)
                return
        self.free += 1

    def _drop(self, client: str, turn: asyncio.Future) -> None:
        turns = self._waiting.get(client)
        if turns is not None and turn in turns:
            turns.remove(turn)
            if not turns:
                del self._waiting[client]


class ClientGone(RuntimeError):
    """The client disconnected while its plan waited for a worker."""


class Planner:
    """Runs :func:`plan_grasps`, at most ``workers`` at once, in processes or threads, with a
    bounded queue in front and a cache of recent plans."""

    def __init__(
        self, workers: int, *, processes: bool, queue: int, cache: int,
        per_client: int | None = None, trials_per_client: int | None = None,
    ) -> None:
        self.workers = workers
        self.processes = processes
        self.queue = queue
        self.per_client = workers + queue if per_client is None else per_client
        #: verification work (lift trials, convex pieces) of one client running at once: below
        #: ``workers``, a worker is always left for another client's plan
        self.trials_per_client = workers if trials_per_client is None else trials_per_client
        self._trial_gates: dict[str, tuple[asyncio.Semaphore, int]] = {}
        self._pool: ProcessPoolExecutor | None = None
        self._pending = 0  # plans admitted: running or waiting
        self._pending_of: dict[str, int] = {}  # the same, by client
        self._slots = FairSlots(workers)
        self._cache: OrderedDict[str, tuple[list, float]] = OrderedDict()
        self._cache_size = cache
        self.cache_hits = 0
        self._inflight: dict[str, asyncio.Future] = {}  # plans being computed, by key

    def _executor(self) -> ProcessPoolExecutor:
        if self._pool is None:
            # spawn: the server has torch's thread pools running, which fork does not survive.
            context = multiprocessing.get_context("spawn")
            self._pool = ProcessPoolExecutor(
                self.workers, mp_context=context, initializer=workers.start,
                initargs=(PLANNER_NICENESS,)
            )
        return self._pool

    async def plan(
        self, request: PlanRequest, *, client: str = "",
        gone: Callable[[], Awaitable[bool]] | None = None,
    ) -> tuple[list, float, bool]:
        """The plan, its planning seconds (verification included) and whether it came from the
        cache or from the same plan another request of the same ``client`` was computing (then
        the seconds are those of the original plan): identical concurrent plans are computed
        once. Its work waits for worker slots in ``client``'s turn (:class:`FairSlots`).
        ``gone``: an async check that the client disconnected, asked once a worker is free."""
        key = f"{client}/{request.key}"  # a client learns nothing of another's plans
        if key in self._cache:
            self._cache.move_to_end(key)
            self.cache_hits += 1
            return (*self._cache[key], True)
        if key in self._inflight:  # the same plan is being computed: share it
            shared = self._inflight[key]
            try:
                return (*await asyncio.shield(shared), True)
            except (ClientGone, PlannerBusy, BrokenProcessPool, asyncio.CancelledError):
                if not (shared.done() and (shared.cancelled() or shared.exception())):
                    raise  # this request was cancelled itself
                # the computing request's client went, or its worker: plan for this one
                return await self.plan(request, client=client, gone=gone)
        shared = asyncio.get_running_loop().create_future()
        self._inflight[key] = shared
        try:
            result = await self._admitted(request, key, client, gone)
        except asyncio.CancelledError:
            shared.cancel()
            raise
        except BaseException as exc:
            shared.set_exception(exc)
            shared.exception()  # retrieved: no "never retrieved" warning when nobody waits
            raise
        else:
            shared.set_result(result)
        finally:
            del self._inflight[key]
        return (*result, False)

    async def _admitted(self, r: PlanRequest, key: str, client: str, gone) -> tuple[list, float]:
        """The plan run by a worker once admitted (bounded queue, and a bound per client),
        verified, then cached under ``key``."""
        if self._pending >= self.workers + self.queue:
            raise PlannerBusy(
                f"{self._pending} grasp plans are running or waiting (at most "
                f"{self.workers + self.queue}); try again shortly"
            )
        if self._pending_of.get(client, 0) >= self.per_client:
            raise PlannerBusy(
                f"this client has {self.per_client} grasp plans running or waiting, the most one "
                "client may (GRASP_CLIENT_PLANS); try again once one is answered"
            )
        self._pending += 1
        self._pending_of[client] = self._pending_of.get(client, 0) + 1
        pieces = None
        try:
            async with self._slots.take(client):
                if gone is not None and await gone():
                    raise ClientGone("the client disconnected while its plan waited")
                if r.verify:  # the lift test's convex pieces, in another worker meanwhile
                    pieces = asyncio.ensure_future(
                        self._trial(partial(decompose, r.vertices, r.faces), client))
                result = await self._call(partial(plan_grasps, r))
            if r.verify:
                start = time.perf_counter()
                await pieces
                ranked = await self._verified(r.vertices, r.faces, result[0], r.verify,
                                              r.support_plane, r.seed, client)
                result = (ranked[:r.top_k], result[1] + time.perf_counter() - start)
        finally:
            self._pending -= 1
            self._pending_of[client] -= 1
            if not self._pending_of[client]:
                del self._pending_of[client]
            if pieces is not None and not pieces.done():
                pieces.cancel()  # the plan failed: nobody needs the pieces
            elif pieces is not None and not pieces.cancelled():
                pieces.exception()  # retrieved: no "never retrieved" warning
        if self._cache_size:
            self._cache[key] = result
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return result

    async def _verified(self, vertices, faces, ranked, n, support_plane, seed, client) -> list:
        """:func:`grasp.ranking.select.verified`, each grasp's trials spread over the workers: every
        trial takes a worker slot of its own, in ``client``'s turn (:class:`FairSlots`)."""
        from grasp.ranking.select import verified

        loop = asyncio.get_running_loop()

        def run(jobs):  # called from a worker thread: the trials of one grasp, at once
            calls = [self._trial(partial(lift_trial, vertices, faces, g, plane, t), client)
                     for _, g, plane, t in jobs]
            future = asyncio.run_coroutine_threadsafe(_gather(calls), loop)
            return future.result()

        return await anyio.to_thread.run_sync(
            lambda: verified(ranked, n, mesh=None, support_plane=support_plane, seed=seed, run=run))

    async def _trial(self, call, client: str):
        """Verification work in a worker once ``client`` has fewer than ``trials_per_client``
        running and its turn gives it a slot."""
        gate, users = self._trial_gates.get(client, (None, 0))
        gate = gate or asyncio.Semaphore(self.trials_per_client)
        self._trial_gates[client] = (gate, users + 1)
        try:
            async with gate, self._slots.take(client):
                return await self._call(call)
        finally:
            gate, users = self._trial_gates[client]
            if users == 1:
                del self._trial_gates[client]
            else:
                self._trial_gates[client] = (gate, users - 1)

    async def _call(self, call):
        """``call`` in a worker process, or a thread (``processes=False``)."""
        if not self.processes:
            return await anyio.to_thread.run_sync(call)  # the slots bound the workers
        pool = self._executor()
        try:
            return await asyncio.get_running_loop().run_in_executor(pool, call)
        except BrokenProcessPool:
            log.error("a planner process died; starting a new pool")
            if self._pool is pool:
                self._pool = None
                pool.shutdown(wait=False, cancel_futures=True)
            raise

    @property
    def pending(self) -> int:
        """Plans admitted and not finished (running or waiting for a worker)."""
        return self._pending

    def warm_up(self) -> list:
        """Start the worker processes and import the planner there; the futures, to wait on."""
        if not self.processes:
            return []
        return [self._executor().submit(_import_planner) for _ in range(self.workers)]

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


async def _gather(calls):
    return await asyncio.gather(*calls)
