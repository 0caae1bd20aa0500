"""The FastAPI app factory: settings in, app out; the model is loaded in the lifespan.

The routers (:mod:`service.api.views`, :mod:`service.api.grasps`, :mod:`service.api.sessions`,
:mod:`service.api.inspector`), the middleware
(:mod:`service.api.middleware`), the error handlers (:mod:`service.api.errors`) and the API document
(:mod:`service.api.openapi`) each live in their own module; this one puts them together.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from functools import partial

import anyio.to_thread
from anyio import CapacityLimiter
from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from service.api import errors, grasps, inspector, openapi, sessions, views
from service.api.middleware import BodyLimit, QueryOnce, TokenGate
from service.engine.pipeline import Pipeline
from service.engine.planning import Planner
from service.intake.memory import return_freed_memory
from service.intake.parsing import BodyParser
from service.services import Services
from service.settings import Settings
from service.store.base import Store
from service.store.sessions import SessionLocks, open_store

log = logging.getLogger(__name__)

#: Seconds between sweeps that delete expired sessions (at most; shorter for short TTLs).
PURGE_INTERVAL_S = 60.0


def create_app(settings: Settings | None = None) -> FastAPI:
    """The service; ``settings`` default to the ``GRASP_*`` environment."""
    settings = settings or Settings()
    app = FastAPI(
        title="mvp-grasp",
        summary="Stream depth views of an object, get a BarrettHand grasp on its completed shape",
        version="0.1.0",
        lifespan=_lifespan,
    )
    app.state.settings = settings
    app.include_router(views.router)  # POST /views (token)
    app.include_router(grasps.router)  # GET /grasp (token)
    app.include_router(sessions.router)  # a session's summary, mesh, occupancy (token)
    app.include_router(inspector.data_router)  # the inspector's observed points, scene (token)
    app.include_router(sessions.health_router)  # /healthz (public)
    app.include_router(inspector.page_router)  # the inspector page (public)
    app.mount("/static/inspector", StaticFiles(directory=inspector.STATIC), name="inspector")
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(QueryOnce)
    app.add_middleware(TokenGate, tokens=settings.tokens())  # added last: runs first
    errors.install(app)
    app.openapi = partial(openapi.document, app)
    return app


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    import torch

    from completion.config import POSED_MODEL
    from completion.model import load_model

    settings: Settings = app.state.settings
    torch.set_num_threads(settings.torch_threads)
    return_freed_memory()  # big arrays given back to the system when freed (service.intake.memory)
    model = await anyio.to_thread.run_sync(load_model, settings.model)
    posed = None  # MVP's sessions with camera poses run the model trained on them
    if settings.model == "mvp":
        posed = await anyio.to_thread.run_sync(load_model, POSED_MODEL)
    store = await anyio.to_thread.run_sync(open_store, settings)
    pipeline = await anyio.to_thread.run_sync(
        lambda: Pipeline(model, store, model_name=settings.model, max_views=settings.max_views,
                         frame_checks=settings.frame_checks(), registered=settings.registered,
                         posed_model=posed)
    )
    app.state.services = Services(
        settings=settings,
        pipeline=pipeline,
        inference=CapacityLimiter(settings.inference_workers),
        planner=Planner(
            settings.planning_workers,
            processes=settings.planning_processes,
            queue=settings.planning_queue,
            cache=settings.plan_cache,
            per_client=settings.client_plans,
            trials_per_client=settings.trials_per_client(),
        ),
        locks=SessionLocks(),
        parser=BodyParser(
            settings.inference_workers,
            max_body_bytes=settings.max_body_bytes,
            body_memory=settings.body_memory_bytes,
            decode_memory=settings.decode_memory_bytes,
            memory_wait_s=settings.memory_wait_s,
            limits=settings.decode_limits(),
            at_once=settings.max_parsing,
        ),
    )
    log.info("model %s (weights %s), store %s", settings.model, pipeline.model_id, store.where)
    # every worker process started (and the planner imported) before /healthz answers: the first
    # requests pay nothing, and a cold server's memory is a warm one's
    started = [*app.state.services.planner.warm_up(), *app.state.services.parser.warm_up()]
    await anyio.to_thread.run_sync(lambda: [f.result() for f in started])
    sweeper = asyncio.create_task(_purge_expired(store))
    try:
        yield
    finally:
        sweeper.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await sweeper
        await anyio.to_thread.run_sync(app.state.services.planner.close)
        app.state.services.parser.close()
        store.close()


async def _purge_expired(store: Store) -> None:
    interval = min(PURGE_INTERVAL_S, store.ttl_s)
    while True:
        await asyncio.sleep(interval)
        try:
            await anyio.to_thread.run_sync(store.purge_expired)
        except Exception:  # a busy or broken store must not end the sweeps
            log.exception("purging expired sessions failed")
