"""The store the settings name, and session locks: :func:`open_store` picks
:class:`service.store.sqlite_store.SQLiteSessionStore` (one SQLite file, the embedded default) or
:class:`service.store.redis_store.RedisSessionStore` for ``GRASP_STORE_URL``. Writes are
compare-and-swap on the view count (see :mod:`service.store.base`); within one process
:class:`SessionLocks` queues the ``POST /views`` of a session so that none has to retry.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING

from service.store.base import Store
from service.store.redis_store import RedisSessionStore
from service.store.sqlite_store import SQLiteSessionStore

if TYPE_CHECKING:
    from service.settings import Settings

log = logging.getLogger(__name__)

def open_store(settings: Settings) -> Store:
    """The store the settings name: Redis for ``store_url``, else the SQLite ``store_path``."""
    limits = dict(
        max_sessions=settings.max_sessions,
        ttl_s=settings.session_ttl_s,
        unseen_ttl_s=settings.unseen_session_ttl_s,
        max_answers=settings.max_answers,
    )
    if settings.store_url is not None:
        return RedisSessionStore(settings.store_url, **limits)
    return SQLiteSessionStore(settings.store_path, **limits)


class SessionLocks:
    """One asyncio lock per session id, dropped when nobody holds or waits for it."""

    def __init__(self) -> None:
        self._locks: dict[str, tuple[asyncio.Lock, int]] = {}

    @asynccontextmanager
    async def hold(self, session_id: str) -> AsyncIterator[None]:
        lock, users = self._locks.get(session_id, (None, 0))
        lock = lock or asyncio.Lock()
        self._locks[session_id] = (lock, users + 1)
        try:
            async with lock:
                yield
        finally:
            lock, users = self._locks[session_id]
            if users == 1:
                del self._locks[session_id]
            else:
                self._locks[session_id] = (lock, users - 1)

    def __len__(self) -> int:
        return len(self._locks)
