"""The session store interface, on both engines: SQLite (embedded) and Redis (shared by replicas).

Redis runs as a real ``redis-server`` (the ``redis_url`` fixture); each test uses its own key
prefix. The two-replica tests run two ``python -m service`` processes on one Redis.
"""

from __future__ import annotations

import sqlite3
import threading
import time
import uuid

import httpx
import numpy as np
import pytest
import redis
from service_helpers import Server, post_concurrently, post_views, reference, save_tiny

from completion.model import load_model
from completion.stream import CompletionStream
from service.load import scene_views
from service.settings import Settings
from service.store.base import ConcurrentUpdate, SessionNotFound, StoreFull
from service.store.redis_store import RedisSessionStore
from service.store.sqlite_store import SQLiteSessionStore


@pytest.fixture(params=["sqlite", "redis"])
def make_store(request, tmp_path):
    """A factory of empty stores of one engine, with the given limits."""
    made = []

    def make(**limits):
        limits = dict(max_sessions=3, ttl_s=60.0) | limits
        if request.param == "sqlite":
            store = SQLiteSessionStore(tmp_path / f"{uuid.uuid4().hex}.sqlite", **limits)
        else:
            url = request.getfixturevalue("redis_url")
            store = RedisSessionStore(url, prefix=f"test:{uuid.uuid4().hex}:", **limits)
        made.append(store)
        return store

    yield make
    for store in made:
        store.close()


def test_create_get_update_delete(make_store):
    store = make_store()
    state = bytes(range(256)) * 1000  # binary, 256 kB like a real stream state
    a = store.create("a", model="m1", state=state, views=1, object_seen=False)
    got = store.get("a")
    assert (got.model, got.views, got.object_seen, got.state) == ("m1", 1, False, state)
    assert got.created == pytest.approx(a.created, abs=1e-3)
    b = store.update(got, state=b"two", views=2, object_seen=True)
    assert store.get("a").state == b"two" and store.get("a").views == 2 and b.object_seen
    with pytest.raises(ConcurrentUpdate):  # stale: computed on top of view 1
        store.update(got, state=b"stale", views=2, object_seen=True)
    assert store.get("a").state == b"two"  # nothing lost
    assert store.count() == 1 and store.delete("a") and not store.delete("a")
    with pytest.raises(SessionNotFound, match="unknown session 'a'"):
        store.get("a")
    with pytest.raises(SessionNotFound):
        store.update(b, state=b"x", views=3, object_seen=True)


def test_full_store_refuses_new_sessions(make_store):
    store = make_store(max_sessions=2)
    for sid in "ab":
        store.create(sid, model="m", state=b"s", views=1, object_seen=True)
    with pytest.raises(StoreFull, match=r"the session store is full \(2 sessions\)"):
        store.create("c", model="m", state=b"s", views=1, object_seen=True)
    with pytest.raises(StoreFull):
        store.ensure_room()
    store.delete("a")
    store.create("c", model="m", state=b"s", views=1, object_seen=True)
    assert store.count() == 2


def test_sessions_expire_unseen_ones_sooner(make_store):
    store = make_store(ttl_s=30.0, unseen_ttl_s=0.3)
    store.create("unseen", model="m", state=b"s", views=1, object_seen=False)
    store.create("seen", model="m", state=b"s", views=1, object_seen=True)
    assert store.count() == 2
    time.sleep(0.5)
    with pytest.raises(SessionNotFound, match="0.3 s while no view had shown the object"):
        store.get("unseen")
    store.purge_expired()
    assert store.get("seen").views == 1 and store.count() == 1


def test_sqlite_file_shrinks_after_deletes(tmp_path):
    path = tmp_path / "store.sqlite"
    store = SQLiteSessionStore(path, max_sessions=100, ttl_s=60.0)
    state = np.random.default_rng(0).bytes(200_000)
    for k in range(40):
        store.create(f"s{k}", model="m", state=state, views=1, object_seen=True)
    with sqlite3.connect(path) as con:  # fold the WAL into the file, as a quiet server does
        con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    full = path.stat().st_size
    assert full > 40 * 200_000
    for k in range(40):
        assert store.delete(f"s{k}")
    with sqlite3.connect(path) as con:
        con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    assert path.stat().st_size < full / 10


def test_redis_expiry_is_redis_ttl(redis_url):
    store = RedisSessionStore(redis_url, prefix="ttl:", max_sessions=5, ttl_s=100.0,
                              unseen_ttl_s=20.0)  # fmt: skip
    store.create("s", model="m", state=b"x", views=1, object_seen=False)
    ttl = store.redis.pttl("ttl:s:s")
    assert 19_000 < ttl <= 20_000
    store.update(store.get("s"), state=b"y", views=2, object_seen=True)
    assert 99_000 < store.redis.pttl("ttl:s:s") <= 100_000
    store.close()


def test_redis_lock_serialises_one_session(redis_url):
    """Two threads (as two replicas) read-modify-write one session under ``exclusive``."""
    stores = [RedisSessionStore(redis_url, prefix="lock:", max_sessions=5, ttl_s=60.0)
              for _ in range(2)]  # fmt: skip
    stores[0].create("s", model="m", state=b"", views=0, object_seen=True)
    applied: list[int] = []

    def writer(store, tag: int) -> None:
        for _ in range(10):
            with store.exclusive("s"):
                record = store.get("s")
                time.sleep(0.002)  # a model step in between
                store.update(record, state=record.state + bytes([tag]), views=record.views + 1,
                             object_seen=True)  # fmt: skip
                applied.append(tag)

    threads = [threading.Thread(target=writer, args=(s, t)) for t, s in enumerate(stores)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    final = stores[0].get("s")
    assert final.views == 20 and list(final.state) == applied  # no retry, no loss, in order


def test_store_url_is_checked():
    with pytest.raises(ValueError, match="store_url"):
        Settings(store_url="http://localhost:6379")
    with pytest.raises(ConnectionError, match="cannot reach the session store"):
        RedisSessionStore("redis://127.0.0.1:1/0", max_sessions=1, ttl_s=1.0)


# --------------------------------------------------------------------------------- replicas


@pytest.fixture(scope="module")
def replicas(tmp_path_factory, redis_url):
    tmp = tmp_path_factory.mktemp("replicas")
    model = save_tiny(tmp / "tiny.pt")
    unused = tmp / "unused.sqlite"  # must stay empty: the sessions live in Redis
    servers = []
    try:
        for _ in range(2):
            servers.append(Server(tmp, model, unused, store_url=redis_url))
        yield model, servers, redis.Redis.from_url(redis_url)
        assert not unused.exists()
    finally:
        for s in servers:
            s.stop()


def stored(r: redis.Redis, session_id: str) -> bytes:
    return r.hget(f"grasp:s:{session_id}", "state")


@pytest.mark.slow
def test_views_alternate_between_two_replicas(replicas, scene):
    model, (a, b), r = replicas
    bodies = scene_views(scene)
    sid, indices = post_views(a.url, bodies[:1])
    for i, body in enumerate(bodies[1:], start=1):
        _, more = post_views((a, b)[i % 2].url, [body], session_id=sid)
        indices += more
    assert indices == list(range(12))
    assert stored(r, sid) == reference(model, bodies).to_bytes()  # the bytes of one process
    grasps = [
        httpx.get(f"{s.url}/grasp", params={"session_id": sid, "n_candidates": 4}, timeout=300)
        for s in (a, b)
    ]
    assert all(g.status_code == 200 for g in grasps), grasps[0].text
    one, two = (g.json() for g in grasps)
    for key in ("views", "grasps"):
        assert one[key] == two[key]
    assert one["grasps"], one["reason"]
    assert httpx.get(f"{b.url}/sessions/{sid}").json()["views"] == 12
    assert httpx.delete(f"{a.url}/sessions/{sid}").status_code == 204
    assert httpx.get(f"{b.url}/sessions/{sid}").status_code == 404


@pytest.mark.slow
def test_concurrent_views_through_both_replicas_are_serialised(replicas):
    model, servers, r = replicas
    sid, order = post_concurrently([s.url for s in servers], threads=6, per_thread=3)
    assert stored(r, sid) == reference(model, order).to_bytes()  # the sequential replay
    stream = CompletionStream.from_bytes(load_model(model), stored(r, sid))
    assert stream.views == len(order) and np.isfinite(stream.completion().probabilities).all()
