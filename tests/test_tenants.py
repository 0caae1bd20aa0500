"""Each client's sessions are its own (service.store.owned): with several tokens, a session
belongs to the token that made it, and every other token is told it does not exist; idempotency
keys are per client, bound to their body, and deleted with their session."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from service_helpers import points_view, settings

from service.app import create_app
from service.store.owned import OwnedStore, client_id
from service.store.sqlite_store import SQLiteSessionStore

A = {"Authorization": "Bearer tokA"}
B = {"Authorization": "Bearer tokB"}


@pytest.fixture
def two_clients(tmp_path, tiny_model):
    with TestClient(create_app(settings(tmp_path, tiny_model, token="tokA,tokB"))) as c:
        yield c


def _every_route(client: TestClient, sid: str, headers: dict) -> dict[str, int]:
    """The status each route of session ``sid`` answers ``headers``'s client."""
    return {
        "GET /sessions/{id}": client.get(f"/sessions/{sid}", headers=headers).status_code,
        "GET mesh": client.get(f"/sessions/{sid}/mesh", headers=headers).status_code,
        "GET occupancy": client.get(f"/sessions/{sid}/occupancy", headers=headers).status_code,
        "GET observed": client.get(f"/sessions/{sid}/observed", headers=headers).status_code,
        "GET scene.glb": client.get(f"/sessions/{sid}/scene.glb", headers=headers).status_code,
        "GET /grasp": client.get("/grasp", params={"session_id": sid},
                                 headers=headers).status_code,
        "POST /views": client.post("/views", json=points_view(seed=3) | {"session_id": sid},
                                   headers=headers).status_code,
        "DELETE": client.delete(f"/sessions/{sid}", headers=headers).status_code,
    }


def test_another_token_finds_no_session_on_any_route(two_clients):
    c = two_clients
    r = c.post("/views", json=points_view(), headers=A | {"Idempotency-Key": "robot-a-view-1"})
    assert r.status_code == 200
    sid = r.json()["session_id"]
    assert set(_every_route(c, sid, B).values()) == {404}
    unknown = c.get("/sessions/0123456789abcdef", headers=B).json()["detail"]
    assert c.get(f"/sessions/{sid}", headers=B).json()["detail"] == unknown.replace(
        "0123456789abcdef", sid)  # word for word what an id that never existed gets
    # tokB replaying tokA's key gets a view of its own, not tokA's session or its id
    replay = c.post("/views", json=points_view(), headers=B | {"Idempotency-Key": "robot-a-view-1"})
    assert replay.status_code == 200 and replay.json()["session_id"] != sid
    assert c.get(f"/sessions/{sid}", headers=A).json()["views"] == 1  # nothing of A's changed
    routes = _every_route(c, sid, A)
    assert routes.pop("DELETE") == 204 and routes.pop("POST /views") == 200
    assert set(routes.values()) <= {200, 409}, routes  # 409: the tiny model may see no object


def test_an_idempotency_key_is_bound_to_its_body_and_dies_with_its_session(two_clients):
    c = two_clients
    first = c.post("/views", json=points_view(), headers=A | {"Idempotency-Key": "k-1"})
    again = c.post("/views", json=points_view(), headers=A | {"Idempotency-Key": "k-1"})
    assert again.json() == first.json()
    other = c.post("/views", json=points_view(seed=5), headers=A | {"Idempotency-Key": "k-1"})
    assert other.status_code == 422
    detail = other.json()["detail"][0]
    assert detail["loc"] == ["header", "idempotency-key"] and "'k-1'" in detail["msg"]
    sid = first.json()["session_id"]
    assert c.get(f"/sessions/{sid}", headers=A).json()["views"] == 1  # the refused body: no view
    assert c.delete(f"/sessions/{sid}", headers=A).status_code == 204
    fresh = c.post("/views", json=points_view(), headers=A | {"Idempotency-Key": "k-1"})
    assert fresh.status_code == 200 and fresh.json()["session_id"] != sid  # a fresh view


def test_sessions_keep_their_owner_through_a_restart(tmp_path, tiny_model):
    made = settings(tmp_path, tiny_model, token="tokA,tokB")
    with TestClient(create_app(made)) as c:
        sid = c.post("/views", json=points_view(), headers=A).json()["session_id"]
    with TestClient(create_app(made)) as c:  # a new process on the same SQLite file
        assert c.get(f"/sessions/{sid}", headers=B).status_code == 404
        assert c.get(f"/sessions/{sid}", headers=A).json()["views"] == 1


def test_one_token_or_none_is_one_client(tmp_path, tiny_model):
    """Behaviour as before tenants: every request of a single-token (or tokenless) service is
    the same client."""
    for token, headers in ((None, {}), ("tokA", A)):
        with TestClient(create_app(settings(tmp_path / str(token), tiny_model,
                                            token=token))) as c:
            sid = c.post("/views", json=points_view(), headers=headers).json()["session_id"]
            assert c.get(f"/sessions/{sid}", headers=headers).status_code == 200


def test_a_file_from_before_owners_opens_with_its_sessions_ownerless(tmp_path):
    """A store file written before owners existed gains the columns when opened: its sessions
    belong to the tokenless client, its answers keep working."""
    import sqlite3

    path = tmp_path / "old.sqlite"
    con = sqlite3.connect(path)
    con.executescript(
        "CREATE TABLE sessions (id TEXT PRIMARY KEY, model TEXT NOT NULL, created REAL NOT NULL,"
        " updated REAL NOT NULL, views INTEGER NOT NULL, object_seen INTEGER NOT NULL,"
        " state BLOB NOT NULL);"
        "CREATE TABLE answers (key TEXT PRIMARY KEY, answer TEXT NOT NULL, expires REAL NOT NULL);"
        "INSERT INTO sessions VALUES ('s1', 'm', 1e12, 1e12, 1, 1, x'00');")
    con.close()
    store = SQLiteSessionStore(path, max_sessions=5, ttl_s=60.0)
    assert store.get("s1").owner == ""
    assert OwnedStore(store, client_id(None)).get("s1").views == 1
    with pytest.raises(LookupError):
        OwnedStore(store, client_id("tokA")).get("s1")


def test_the_redis_store_keeps_the_owner(redis_url):
    from service.store.redis_store import RedisSessionStore

    store = RedisSessionStore(redis_url, prefix="owners:", max_sessions=5, ttl_s=60.0)
    mine, theirs = OwnedStore(store, client_id("tokA")), OwnedStore(store, client_id("tokB"))
    record = mine.create("s1", model="m", state=b"x", views=1, object_seen=True)
    assert store.get("s1").owner == record.owner == client_id("tokA")
    assert store.update(record, state=b"y", views=2, object_seen=True).owner == record.owner
    with pytest.raises(LookupError):
        theirs.get("s1")
    assert not theirs.delete("s1") and mine.get("s1").views == 2
    assert mine.delete("s1")
