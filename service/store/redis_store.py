"""Sessions in Redis (``GRASP_STORE_URL=redis://host:port/db``): replicas share every session.

Layout, all under one key prefix (``grasp:`` by default):

- ``<prefix>s:<id>``: a hash with the session's fields (``model``, ``created``, ``updated``,
  ``views``, ``seen``, ``state``); Redis expires it ``ttl`` seconds after its last view
  (the shorter ``unseen_ttl_s`` while no view has shown the object);
- ``<prefix>live``: a sorted set of the session ids scored by their expiry time, for
  ``max_sessions`` and ``/healthz`` (entries past their score are dropped on every count);
- ``<prefix>answer:<key>``: a hash (``answer``, ``digest``, ``session``) kept for a view sent with
  an ``Idempotency-Key`` (the key scoped by its client, :mod:`service.store.owned`) as long as a
  session lives; ``<prefix>answers:<id>`` is the set of a session's answer keys, deleted with it,
  and ``<prefix>answers-of:<owner>`` a sorted set of a client's answer keys by time, which keeps
  its newest ``max_answers``;
- ``<prefix>lock:<id>``: a redis-py lock held while one replica applies a view to the session,
  so that views sent to different replicas queue instead of retrying. It is a short lease
  (``GRASP_LOCK_LEASE_S``, 5 s), renewed from a background thread while its holder works
  (:class:`Lease`): a live holder keeps it for as long as its view takes, a replica that dies
  holding it blocks that session for at most one lease. :meth:`RedisSessionStore.try_lock`
  never waits; the service polls it from its event loop, so a view waiting for a lock holds no
  inference slot and delays no other session.

Creation and updates are Lua scripts, atomic on the server: a view is stored only on top of the
state it was computed from (compare-and-swap on the view count), so each view is applied once
and in order, whichever replica receives it.
"""

from __future__ import annotations

import logging
import threading
import time
import weakref
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import redis

from service.store.base import (
    LEASE_S,
    MAX_ANSWERS,
    POLL_S,
    WAIT_LEASES,
    ConcurrentUpdate,
    KeptAnswer,
    SessionNotFound,
    SessionRecord,
    Store,
)

log = logging.getLogger(__name__)

#: KEYS: session hash, live set. ARGV: id, now, max, model, views, seen, state, ttl_ms, expiry,
#: owner.
_CREATE = """
redis.call('ZREMRANGEBYSCORE', KEYS[2], '-inf', ARGV[2])
if redis.call('ZCARD', KEYS[2]) >= tonumber(ARGV[3]) then return 'full' end
redis.call('HSET', KEYS[1], 'model', ARGV[4], 'created', ARGV[2], 'updated', ARGV[2],
           'views', ARGV[5], 'seen', ARGV[6], 'state', ARGV[7], 'owner', ARGV[10])
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

#: KEYS: session hash, live set, the session's answer set. ARGV: id.
_DELETE = """
local deleted = redis.call('DEL', KEYS[1])
redis.call('ZREM', KEYS[2], ARGV[1])
for _, key in ipairs(redis.call('SMEMBERS', KEYS[3])) do redis.call('DEL', key) end
redis.call('DEL', KEYS[3])
return deleted
"""

#: KEYS: answer hash, its session's answer set, its owner's answers by time.
#: ARGV: answer, digest, session id, ttl_ms, now, the oldest time still alive, max_answers.
_REMEMBER = """
redis.call('HSET', KEYS[1], 'answer', ARGV[1], 'digest', ARGV[2], 'session', ARGV[3])
redis.call('PEXPIRE', KEYS[1], ARGV[4])
redis.call('SADD', KEYS[2], KEYS[1])
redis.call('PEXPIRE', KEYS[2], ARGV[4])
redis.call('ZADD', KEYS[3], ARGV[5], KEYS[1])
redis.call('PEXPIRE', KEYS[3], ARGV[4])
redis.call('ZREMRANGEBYSCORE', KEYS[3], '-inf', '(' .. ARGV[6])
local over = redis.call('ZCARD', KEYS[3]) - tonumber(ARGV[7])
if over > 0 then
  for _, key in ipairs(redis.call('ZRANGE', KEYS[3], 0, over - 1)) do redis.call('DEL', key) end
  redis.call('ZREMRANGEBYRANK', KEYS[3], 0, over - 1)
end
"""

_FIELDS = ("model", "created", "updated", "views", "seen", "state", "owner")

class Lease:
    """This process's hold on a session's lock: a thread renews it every third of the lease
    until :meth:`release`, so a holder never loses it however long its view takes.

    A lease that is dropped without :meth:`release` (a bug) stops being renewed when it is
    garbage-collected, and the lock expires one lease later.
    """

    def __init__(self, lock: redis.lock.Lock, session_id: str, lease_s: float) -> None:
        self.lock = lock
        self.session_id = session_id
        self._stop = threading.Event()
        self._lost = threading.Event()  # renewal failed: another holder may have the lock
        self._renewer = threading.Thread(
            target=_renew,
            args=(lock, session_id, lease_s / 3, self._stop, self._lost),
            name=f"lease-{session_id[:16]}",
            daemon=True,
        )
        weakref.finalize(self, self._stop.set)
        self._renewer.start()

    @property
    def lost(self) -> bool:
        """Whether a renewal found the lock gone (Redis restarted, or the renewer stalled for
        a whole lease); the compare-and-swap still guards the view's write."""
        return self._lost.is_set()

    def release(self) -> None:
        """Stop renewing and free the lock (quick; call it once)."""
        self._stop.set()
        self._renewer.join()
        try:
            self.lock.release()
        except redis.exceptions.LockError:  # expired or taken over: the CAS still guarded it
            log.warning("the lock of session %s expired while a view was applied", self.session_id)


def _renew(
    lock: redis.lock.Lock,
    session_id: str,
    every_s: float,
    stop: threading.Event,
    lost: threading.Event,
) -> None:
    """Reset the lock's expiry to a whole lease every ``every_s`` until ``stop`` is set.

    Holds no reference to the :class:`Lease`, so that a dropped lease can be collected."""
    while not stop.wait(every_s):
        try:
            lock.reacquire()
        except redis.exceptions.LockError:
            log.warning("the lock of session %s was lost while a view was applied", session_id)
            lost.set()
            return
        except redis.RedisError as exc:  # a blip: try again before the lease runs out
            log.warning("renewing the lock of session %s failed: %s", session_id, exc)


class RedisSessionStore(Store):
    """The :class:`~service.store.base.Store` interface on a Redis server (redis-py)."""

    def __init__(
        self,
        url: str,
        *,
        max_sessions: int,
        ttl_s: float,
        unseen_ttl_s: float | None = None,
        prefix: str = "grasp:",
        max_answers: int = MAX_ANSWERS,
        clock: Callable[[], float] = time.time,
    ) -> None:
        super().__init__(max_sessions=max_sessions, ttl_s=ttl_s, unseen_ttl_s=unseen_ttl_s,
                         max_answers=max_answers)
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
        self._delete = self.redis.register_script(_DELETE)
        self._remember = self.redis.register_script(_REMEMBER)
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
        model, created, updated, views, seen, state, owner = values
        return SessionRecord(
            session_id,
            model.decode(),
            float(created),
            float(updated),
            int(views),
            seen == b"1",
            bytes(state),
            (owner or b"").decode(),
        )  # Redis's own expiry decides when it is gone

    def count(self) -> int:
        with self.redis.pipeline() as pipe:
            pipe.zremrangebyscore(self._live, "-inf", self.clock())
            pipe.zcard(self._live)
            _, n = pipe.execute()
        return int(n)

    # ---------------------------------------------------------------------------- writes
    def create(
        self, session_id: str, *, model: str, state: bytes, views: int, object_seen: bool,
        owner: str = "",
    ) -> SessionRecord:
        now = self.clock()
        ttl_ms, expiry = self._expiry(object_seen, now)
        answer = self._create(
            keys=[self._key(session_id), self._live],
            args=[session_id, repr(now), self.max_sessions, model, views, int(object_seen),
                  state, ttl_ms, repr(expiry), owner],
        )  # fmt: skip
        if answer == b"full":
            raise self._full()
        return SessionRecord(session_id, model, now, now, views, object_seen, state, owner)

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
            record.id, record.model, record.created, now, views, object_seen, state, record.owner
        )

    def delete(self, session_id: str) -> bool:
        keys = [self._key(session_id), self._live, f"{self.prefix}answers:{session_id}"]
        return int(self._delete(keys=keys, args=[session_id])) > 0

    def recall(self, key: str) -> KeptAnswer | None:
        values = self.redis.hmget(f"{self.prefix}answer:{key}", ("answer", "digest", "session"))
        return None if values[0] is None else KeptAnswer(*(v.decode() for v in values))

    def remember(self, key: str, kept: KeptAnswer, *, owner: str = "") -> None:
        now = self.clock()
        keys = [f"{self.prefix}answer:{key}", f"{self.prefix}answers:{kept.session_id}",
                f"{self.prefix}answers-of:{owner}"]
        self._remember(keys=keys, args=[kept.answer, kept.digest, kept.session_id,
                                        max(1, round(1000 * self.ttl_s)), repr(now),
                                        repr(now - self.ttl_s), self.max_answers])

    def purge_expired(self) -> int:
        """Redis deletes expired sessions itself; this drops their ids from the live set."""
        return int(self.redis.zremrangebyscore(self._live, "-inf", self.clock()))

    def try_lock(self, session_id: str, *, lease_s: float = LEASE_S) -> Lease | None:
        """The session's lock if it is free now (None while another holder has it); never
        waits. Held until :meth:`Lease.release`, renewed meanwhile, for ``lease_s`` seconds
        after this process dies."""
        lock = self.redis.lock(
            f"{self.prefix}lock:{session_id}", timeout=lease_s, thread_local=False
        )  # not thread-local: taken, renewed and released by different threads
        if not lock.acquire(blocking=False):
            return None
        return Lease(lock, session_id, lease_s)

    @contextmanager
    def exclusive(self, session_id: str, *, lease_s: float = LEASE_S) -> Iterator[None]:
        """Hold the session's lock across replicas while one view is applied, waiting for it in
        this thread (at most ``WAIT_LEASES`` leases, then ConcurrentUpdate). The service does
        not wait here: it polls :meth:`try_lock` from its event loop."""
        wait_s = WAIT_LEASES * lease_s
        deadline = time.monotonic() + wait_s
        while (lease := self.try_lock(session_id, lease_s=lease_s)) is None:
            if time.monotonic() >= deadline:
                raise ConcurrentUpdate(
                    f"session {session_id!r} stayed locked by another replica for {wait_s:g} s; "
                    "send the view again"
                )
            time.sleep(POLL_S)
        try:
            yield
        finally:
            lease.release()

    def close(self) -> None:
        self.redis.close()
