"""Session locks across replicas (Redis): short leases renewed by their holder, awaited outside
the inference slots.

A replica that dies holding a session's lock leaves ``<prefix>lock:<id>`` behind; the tests plant
one as it does (``SET grasp:lock:<id> <token> PX <ms>``) and check that nothing but that session
waits, and that session no longer than one lease. Redis is a real ``redis-server`` (the
``redis_url`` fixture); the service is a real ``python -m service`` (tests/service_helpers.py).
"""

from __future__ import annotations

import gc
import math
import threading
import time

import httpx
import pytest
import redis
from service_helpers import Server, points_view, post_views

from service.settings import Settings
from service.store.base import WAIT_LEASES, ConcurrentUpdate, KeptAnswer
from service.store.redis_store import RedisSessionStore

LEASE_S = Settings().lock_lease_s  # the default, as a deployment runs it
INFERENCE_WORKERS = 2  # Server's setting: two locked sessions would fill every slot


def _store(redis_url: str, prefix: str) -> RedisSessionStore:
    return RedisSessionStore(redis_url, prefix=prefix, max_sessions=5, ttl_s=60.0)


# ------------------------------------------------------------------------------- the store


def test_a_holder_working_longer_than_the_lease_keeps_the_lock(redis_url):
    one, other = _store(redis_url, "renew:"), _store(redis_url, "renew:")
    lease = one.try_lock("s", lease_s=0.5)
    assert lease is not None
    for _ in range(10):  # 2.5 s: five leases
        time.sleep(0.25)
        assert other.try_lock("s", lease_s=0.5) is None
        assert 0 < one.redis.pttl("renew:lock:s") <= 500
    assert not lease.lost
    lease.release()
    assert one.redis.exists("renew:lock:s") == 0
    again = other.try_lock("s", lease_s=0.5)  # free at once after the release
    assert again is not None and not again.lost
    again.release()


def test_a_dead_holders_lock_expires_after_one_lease(redis_url):
    store = _store(redis_url, "dead:")
    store.redis.set("dead:lock:s", "a-dead-replica", px=400)
    assert store.try_lock("s", lease_s=0.4) is None
    start = time.monotonic()
    with store.exclusive("s", lease_s=0.4):  # waits in this thread for the expiry
        waited = time.monotonic() - start
    assert 0.2 < waited < 0.4 + 0.5


def test_a_dropped_lease_stops_being_renewed(redis_url):
    """A lease lost by its holder without release (a bug) expires like a dead replica's."""
    store = _store(redis_url, "dropped:")
    lease = store.try_lock("s", lease_s=0.3)
    assert lease is not None
    del lease
    gc.collect()
    time.sleep(0.3 + 0.15)
    taken = store.try_lock("s", lease_s=0.3)
    assert taken is not None
    taken.release()


def test_exclusive_gives_up_after_two_leases(redis_url):
    store = _store(redis_url, "stuck:")
    store.redis.set("stuck:lock:s", "x", px=30_000)
    start = time.monotonic()
    with pytest.raises(ConcurrentUpdate, match="stayed locked by another replica"):
        with store.exclusive("s", lease_s=0.2):
            pass
    assert WAIT_LEASES * 0.2 <= time.monotonic() - start < WAIT_LEASES * 0.2 + 1.0


# ------------------------------------------------------------------------------- a replica


@pytest.fixture(scope="module")
def replica(tmp_path_factory, tiny_model, redis_url):
    tmp = tmp_path_factory.mktemp("replica_locks")
    server = Server(tmp, tiny_model, tmp / "unused.sqlite", store_url=redis_url)
    try:
        yield server, redis.Redis.from_url(redis_url)
    finally:
        server.stop()


def _timed_view(url: str, session_id: str | None, seed: int) -> tuple[httpx.Response, float]:
    body = points_view(seed=seed) | ({} if session_id is None else {"session_id": session_id})
    start = time.monotonic()
    r = httpx.post(f"{url}/views", json=body, timeout=120)
    return r, time.monotonic() - start


def _dead_replica_scene(replica, px_ms: int):
    """Plant a dead replica's lock on two sessions (as many as there are inference slots) and
    send a view to each, then a second view to the first (it queues in the replica); meanwhile
    time a view to a third session and one to a new session. Returns the (response, seconds) of
    the three locked views and of the two others."""
    server, r = replica
    locked = [post_views(server.url, [points_view(seed=k)])[0] for k in range(INFERENCE_WORKERS)]
    free, _ = post_views(server.url, [points_view(seed=7)])
    for sid in locked:
        r.set(f"grasp:lock:{sid}", "a-dead-replica", px=px_ms)
    to_locked = [*locked, locked[0]]
    answers: list = [None] * len(to_locked)

    def send(k: int) -> None:
        answers[k] = _timed_view(server.url, to_locked[k], 10 + k)

    threads = [threading.Thread(target=send, args=(k,)) for k in range(len(to_locked))]
    for t in threads:
        t.start()
    time.sleep(0.5)  # the locked views are waiting now
    others = [_timed_view(server.url, free, 2), _timed_view(server.url, None, 3)]
    for t in threads:
        t.join()
    return answers, others


@pytest.mark.slow
def test_a_lock_left_for_one_lease_delays_only_its_session(replica):
    locked, others = _dead_replica_scene(replica, px_ms=round(LEASE_S * 1000))
    print(f"\nlease {LEASE_S:g} s: other session, new session "
          f"{[round(s, 3) for _, s in others]} s; locked sessions "
          f"{[round(s, 3) for _, s in locked]} s")  # fmt: skip
    for r, seconds in others:
        assert r.status_code == 200, r.text
        assert seconds < 1.0
    for r, seconds in locked:
        assert r.status_code == 200, r.text
        assert LEASE_S - 1.0 < seconds < LEASE_S + 1.0  # waited for the expiry, then went on
    assert sorted(r.json()["view_index"] for r, _ in locked) == [1, 1, 2]


@pytest.mark.slow
def test_a_lock_left_for_30_s_delays_no_other_session(replica):
    locked, others = _dead_replica_scene(replica, px_ms=30_000)
    print(f"\nPX 30000: other session, new session {[round(s, 3) for _, s in others]} s; "
          f"locked sessions {[round(s, 3) for _, s in locked]} s")  # fmt: skip
    for r, seconds in others:
        assert r.status_code == 200, r.text
        assert seconds < 1.0
    wait_s = WAIT_LEASES * LEASE_S
    for r, seconds in locked:
        assert r.status_code == 503, r.text
        assert r.headers["Retry-After"] == str(math.ceil(LEASE_S))
        assert "still locked by another replica" in r.json()["detail"]
        assert wait_s - 0.6 < seconds < wait_s + 1.0


def test_both_stores_keep_an_idempotent_answer_for_a_sessions_life(redis_url, tmp_path):
    """Store.recall/remember, behind POST /views's Idempotency-Key: in Redis (shared by the
    replicas) and in SQLite, with the body's digest and the session; gone once a session would
    be, or once its session is deleted; each owner keeps its newest ``max_answers``."""
    from service.store.sqlite_store import SQLiteSessionStore

    now = [1000.0]
    sqlite = SQLiteSessionStore(tmp_path / "s.sqlite", max_sessions=5, ttl_s=60.0,
                                max_answers=2, clock=lambda: now[0])
    redis_store = RedisSessionStore(redis_url, prefix="idem:", max_sessions=5, ttl_s=60.0,
                                    max_answers=2)
    stores = [redis_store, sqlite]
    for s in stores:
        assert s.recall("k1") is None
        s.create("s1", model="m", state=b"x", views=1, object_seen=True, owner="a")
        s.remember("k1", KeptAnswer('{"view_index": 0}', "d1", "s1"), owner="a")
        assert s.recall("k1") == KeptAnswer('{"view_index": 0}', "d1", "s1")
        s.remember("k2", KeptAnswer("{}", "d2", "s2"), owner="a")
        s.remember("k3", KeptAnswer("{}", "d3", "s2"), owner="b")
        assert s.recall("k1") is not None  # a's two, b's one: all kept
        s.remember("k4", KeptAnswer("{}", "d4", "s2"), owner="a")
        assert s.recall("k1") is None and s.recall("k2") and s.recall("k3") and s.recall("k4")
        s.remember("k5", KeptAnswer("{}", "d5", "s1"), owner="b")
        assert s.delete("s1")  # its answers go with it, the others stay
        assert s.recall("k5") is None and s.recall("k4") is not None
    now[0] += 61  # the SQLite store's clock: past a session's life
    assert stores[1].recall("k4") is None
    stores[1].purge_expired()
    assert stores[0].redis.pttl(f"{stores[0].prefix}answer:k4") > 50_000  # Redis expires it


