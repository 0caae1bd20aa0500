"""The running service's parts, as the lifespan builds them (:class:`Services`): the settings,
the pipeline, the planner, the thread limit, the session locks and the body parser.

A view to an existing session holds the session (:meth:`Services.exclusive`): views of it in
this replica queue on an asyncio lock, and the store's lock across replicas is polled from the
event loop. Waiting for either holds no inference slot, so a session whose lock a dead replica
left behind delays no other session, and its own views wait at most about one lease
(``GRASP_LOCK_LEASE_S``) before the lock expires; after ``WAIT_LEASES`` leases they get 503.
"""

from __future__ import annotations

import math
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass
from functools import partial
from typing import TypeVar

import anyio
import anyio.to_thread
from anyio import CapacityLimiter
from fastapi import HTTPException, status

from service.engine.pipeline import Pipeline
from service.engine.planning import Planner
from service.intake.parsing import BodyParser
from service.settings import Settings
from service.store.base import POLL_S, WAIT_LEASES
from service.store.sessions import SessionLocks

T = TypeVar("T")


@dataclass
class Services:
    """Everything the lifespan builds: settings, the pipeline, the planner, the thread limit."""

    settings: Settings
    pipeline: Pipeline
    inference: CapacityLimiter  # model steps and completions running at once
    planner: Planner  # grasp plans, in worker processes or threads
    locks: SessionLocks  # POST /views of one session, one after the other
    parser: BodyParser  # POST /views bodies, parsed off the event loop

    async def infer(self, fn: Callable[..., T], *args, **kwargs) -> T:
        """Run blocking model work in a worker thread, at most ``inference_workers`` at once."""
        return await anyio.to_thread.run_sync(partial(fn, *args, **kwargs), limiter=self.inference)

    async def io(self, fn: Callable[..., T], *args, **kwargs) -> T:
        """Run a quick store call in a worker thread, without queueing behind the model."""
        return await anyio.to_thread.run_sync(partial(fn, *args, **kwargs))

    @asynccontextmanager
    async def exclusive(self, session_id: str) -> AsyncIterator[None]:
        """Hold the session while one view is applied to it: behind the views of it that came
        to this replica first, then with its lock across replicas. Waits on the event loop,
        never in an inference slot; 503 when another replica still holds the lock
        ``WAIT_LEASES`` leases after this view came."""
        deadline = time.monotonic() + WAIT_LEASES * self.settings.lock_lease_s
        async with self.locks.hold(session_id):
            lease = await self._lock(session_id, deadline)
            try:
                yield
            finally:
                with anyio.CancelScope(shield=True):
                    await self.io(lease.release)

    async def _lock(self, session_id: str, deadline: float):
        """Poll the session's lock across replicas until this replica holds it."""
        while True:
            with anyio.CancelScope(shield=True):  # a lock taken is never dropped unreleased
                lease = await self.io(
                    self.pipeline.store.try_lock, session_id, lease_s=self.settings.lock_lease_s
                )
            if lease is not None:
                return lease
            if time.monotonic() >= deadline:
                raise self._busy(session_id)
            await anyio.sleep(POLL_S)

    def _busy(self, session_id: str) -> HTTPException:
        lease_s = self.settings.lock_lease_s
        return HTTPException(
            status.HTTP_503_SERVICE_UNAVAILABLE,
            f"session {session_id!r} was still locked by another replica "
            f"{WAIT_LEASES * lease_s:g} s after this view came (a replica that dies holding the "
            f"lock blocks its session for GRASP_LOCK_LEASE_S = {lease_s:g} s); send the view "
            "again",
            headers={"Retry-After": str(math.ceil(lease_s))},
        )
