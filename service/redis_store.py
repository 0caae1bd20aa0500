"""Sessions in Redis (``GRASP_STORE_URL=redis://host:port/db``): replicas share every session.

Layout, all under one key prefix (``grasp:`` by default):

- ``<prefix>s:<id>``: a hash with the session's fields (``model``, ``created``, ``updated``,
  ``views``, ``seen``, ``state``); Redis expires it ``ttl`` seconds after its last view
  (the shorter ``unseen_ttl_s`` while no view has shown the object);
- ``<prefix>live``: a sorted set of the session ids scored by their expiry time, for
  ``max_sessions`` and ``/healthz`` (entries past their score are dropped on every count);
- ``<prefix>lock:<id>``: a redis-py lock held while one replica applies a view to the session,
  so that views sent to different replicas queue instead of retrying.

Creation and updates are Lua scripts, atomic on the server: a view is stored only on top of the
state it was computed from (compare-and-swap on the view count), so each view is applied once
and in order, whichever replica receives it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import redis

from service.store import ConcurrentUpdate, SessionNotFound, SessionRecord, Store

log = logging.getLogger(__name__)

#: KEYS: session hash, live set. ARGV: id, now, max, model, views, seen, state, ttl_ms, expiry.
_CREATE = """
redis.call('ZREMRANGEBYSCORE', KEYS[2], '-inf', ARGV[2])
if redis.call('ZCARD', KEYS[2]) >= tonumber(ARGV[3]) then return 'full' end
redis.call('HSET', KEYS[1], 'model', ARGV[4], 'created', ARGV[2], 'updated', ARGV[2],
           'views', ARGV[5], 'seen', ARGV[6], 'state', ARGV[7])
redis.call('PEXPIRE', KEYS[1], ARGV[8])
redis.call('ZADD', KEYS[2], ARGV[9], ARGV[1])
return 'ok'
"""

#: KEYS: session hash, live set. ARGV: id, expected views, now, views, seen, state, ttl_ms, expiry.
_UPDATE = """
local views = redis.call('HGET', KEYS[1], 'views')
if not views then return 'gone' end
if views ~= ARGV[2] then return 'conflict' end
redis.call('HSET', KEYS[1], 'updated', ARGV[3], 'views', ARGV[4], 'seen', ARGV[5],
           'state', ARGV[6])
redis.call('PEXPIRE', KEYS[1], ARGV[7])
redis.call('ZADD', KEYS[2], ARGV[8], ARGV[1])
return 'ok'
"""

_FIELDS = ("model", "created", "updated", "views", "seen", "state")

#: Seconds one replica may hold a session's lock (a view takes well under one); a replica that
#: dies holding it blocks that session for at most this long.
LOCK_S = 30.0


class RedisSessionStore(Store):
    """The :class:`~service.store.Store` interface on a Redis server (redis-py)."""

    def __init__(
        self,
        url: str,
        *,
        max_sessions: int,
        ttl_s: float,
        unseen_ttl_s: float | None = None,
        prefix: str = "grasp:",
        clock: Callable[[], float] = time.time,
    ) -> None:
        super().__init__(max_sessions=max_sessions, ttl_s=ttl_s, unseen_ttl_s=unseen_ttl_s)
        self.url = url
        self.prefix = prefix
        self.clock = clock
        self.redis = redis.Redis.from_url(url, socket_timeout=30, health_check_interval=30)
        try:
            self.redis.ping()
        except redis.RedisError as exc:
            raise ConnectionError(f"cannot reach the session store at {url}: {exc}") from exc
        self._create = self.redis.register_script(_CREATE)
        self._update = self.redis.register_script(_UPDATE)
        self._live = f"{prefix}live"

    @property
    def where(self) -> str:
        return self.url

    def _key(self, session_id: str) -> str:
        return f"{self.prefix}s:{session_id}"

    def _expiry(self, object_seen: bool, now: float) -> tuple[int, float]:
        ttl = self.ttl_s if object_seen else self.unseen_ttl_s
        return max(1, round(ttl * 1000)), now + ttl

    # ---------------------------------------------------------------------------- reads
    def get(self, session_id: str) -> SessionRecord:
        values = self.redis.hmget(self._key(session_id), _FIELDS)
        if values[0] is None:
            raise SessionNotFound(self.not_found_message(session_id))
        model, created, updated, views, seen, state = values
        return SessionRecord(
            session_id,
            model.decode(),
            float(created),
            float(updated),
            int(views),
            seen == b"1",
            bytes(state),
        )  # Redis's own expiry decides when it is gone

    def count(self) -> int:
        with self.redis.pipeline() as pipe:
            pipe.zremrangebyscore(self._live, "-inf", self.clock())
            pipe.zcard(self._live)
            _, n = pipe.execute()
        return int(n)

    # ---------------------------------------------------------------------------- writes
    def create(
        self, session_id: str, *, model: str, state: bytes, views: int, object_seen: bool
    ) -> SessionRecord:
        now = self.clock()
        ttl_ms, expiry = self._expiry(object_seen, now)
        answer = self._create(
            keys=[self._key(session_id), self._live],
            args=[session_id, repr(now), self.max_sessions, model, views, int(object_seen),
                  state, ttl_ms, repr(expiry)],
        )  # fmt: skip
        if answer == b"full":
            raise self._full()
        return SessionRecord(session_id, model, now, now, views, object_seen, state)

    def update(
        self, record: SessionRecord, *, state: bytes, views: int, object_seen: bool
    ) -> SessionRecord:
        now = self.clock()
        ttl_ms, expiry = self._expiry(object_seen, now)
        answer = self._update(
            keys=[self._key(record.id), self._live],
            args=[record.id, record.views, repr(now), views, int(object_seen), state, ttl_ms,
                  repr(expiry)],
        )  # fmt: skip
        if answer == b"gone":
            raise SessionNotFound(self.not_found_message(record.id))
        if answer == b"conflict":
            raise ConcurrentUpdate(f"session {record.id!r} changed while a view was applied")
        return SessionRecord(
            record.id, record.model, record.created, now, views, object_seen, state
        )

    def delete(self, session_id: str) -> bool:
        with self.redis.pipeline() as pipe:  # MULTI/EXEC
            pipe.delete(self._key(session_id))
            pipe.zrem(self._live, session_id)
            deleted, _ = pipe.execute()
        return deleted > 0

    def purge_expired(self) -> int:
        """Redis deletes expired sessions itself; this drops their ids from the live set."""
        return int(self.redis.zremrangebyscore(self._live, "-inf", self.clock()))

    @contextmanager
    def exclusive(self, session_id: str) -> Iterator[None]:
        """Hold the session's lock across replicas while one view is applied."""
        lock = self.redis.lock(
            f"{self.prefix}lock:{session_id}", timeout=LOCK_S, blocking_timeout=LOCK_S
        )
        if not lock.acquire():
            raise ConcurrentUpdate(
                f"session {session_id!r} stayed locked by another replica for {LOCK_S:g} s; "
                "send the view again"
            )
        try:
            yield
        finally:
            try:
                lock.release()
            except redis.exceptions.LockError:  # held past LOCK_S: the CAS still guarded it
                log.warning("the lock of session %s expired while a view was applied", session_id)

    def close(self) -> None:
        self.redis.close()
