"""Connections to a real ``python -m service`` (service/server/connections.py): early answers that
every client reads, deadlines for a request's head and body, a cap on connections per client
address."""

from __future__ import annotations

import http.client
import importlib.util
import json
import socket
import time
import urllib.error
import urllib.request

import httpx
import pytest
from service_helpers import Server, points_view

MB = 1024 * 1024
TOKEN = "s3cret"
HEAD_S, BODY_S, PER_CLIENT = 2.0, 3.0, 4
JSON = {"content-type": "application/json"}
AUTH = JSON | {"authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def server(tmp_path_factory, tiny_model):
    tmp = tmp_path_factory.mktemp("connections")
    s = Server(tmp, tiny_model, tmp / "store.sqlite", token=TOKEN, max_body_bytes=8 * MB,
               header_timeout_s=HEAD_S, body_timeout_s=BODY_S,
               max_connections_per_client=PER_CLIENT, planning_processes="false")  # fmt: skip
    yield s
    s.stop()


def _urllib(url: str, body: bytes, headers: dict) -> tuple[int, dict]:
    """urllib sends ``Connection: close`` and the whole body, and only then reads."""
    request = urllib.request.Request(f"{url}/views", data=body, headers=headers)
    with pytest.raises(urllib.error.HTTPError) as caught:
        urllib.request.urlopen(request, timeout=30)
    return caught.value.code, json.loads(caught.value.read())


def _http_client(port: int, body: bytes, headers: dict) -> tuple[int, dict, str | None]:
    """http.client keeps the connection alive, sends the whole body, then reads."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        conn.request("POST", "/views", body=body, headers=headers)
        r = conn.getresponse()
        return r.status, json.loads(r.read()), r.getheader("connection")
    finally:
        conn.close()


def test_an_early_401_reaches_clients_that_send_the_whole_body_first(server):
    body = b"x" * (8 * MB)  # the server answers after ~64 kB and discards the rest
    expected = httpx.post(f"{server.url}/views", json={}).json()  # a small body's 401
    assert "bearer" in expected["detail"].lower()
    for _ in range(3):  # a reset was the rule, not a race: every try would have failed
        assert _urllib(server.url, body, JSON) == (401, expected)
    assert _http_client(server.port, body, JSON) == (401, expected, "close")
    if importlib.util.find_spec("requests") is not None:  # not a dependency; often there
        import requests

        r = requests.post(f"{server.url}/views", data=body, headers=JSON, timeout=30)
        assert (r.status_code, r.json()) == (401, expected)
    r = httpx.post(f"{server.url}/views", content=body, headers=JSON, timeout=30)
    assert (r.status_code, r.json()) == (401, expected)


def test_an_early_413_reaches_urllib_and_the_drain_is_bounded(server):
    over = b"x" * (12 * MB)  # over the 8 MB limit, within the 2 x 8 MB drained after the 413
    status, answer = _urllib(server.url, over, AUTH)
    assert status == 413 and "GRASP_MAX_BODY_BYTES" in answer["detail"]
    assert _http_client(server.port, over, AUTH) == (413, answer, "close")
    huge = urllib.request.Request(f"{server.url}/views", data=b"x" * (40 * MB), headers=AUTH)
    with pytest.raises(OSError) as caught:  # not read to its end: cut off after 16 MB
        urllib.request.urlopen(huge, timeout=30)
    assert not isinstance(caught.value, urllib.error.HTTPError)
    assert httpx.get(f"{server.url}/healthz").status_code == 200


def test_an_early_answer_on_a_keep_alive_connection_skips_the_body_and_goes_on(server):
    """A 404 sent before the body was read, without Connection: close: the rest of the body is
    discarded and the next request on the same connection is served."""
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
    try:
        conn.request("POST", "/no-such-route", body=b"x" * (8 * MB), headers=AUTH)
        r = conn.getresponse()
        assert (r.status, r.read(), r.getheader("connection")) == (404, b'{"detail":"Not Found"}',
                                                                    None)  # fmt: skip
        sock = conn.sock
        conn.request("GET", "/healthz")
        assert conn.getresponse().status == 200 and conn.sock is sock
    finally:
        conn.close()


def _wait_for_answer(sock: socket.socket, trickle: bytes) -> tuple[bytes | None, float]:
    """Send ``trickle`` a byte a second until the server answers or closes: (what it sent, b""
    for a close, None for a reset; seconds). Gives up after 10 s."""
    sock.settimeout(1.0)
    start = time.monotonic()
    for byte in trickle[:10]:
        try:
            sock.sendall(bytes([byte]))
            return sock.recv(4096), time.monotonic() - start
        except TimeoutError:
            continue
        except ConnectionError:
            return None, time.monotonic() - start
    raise AssertionError(f"still connected after {time.monotonic() - start:.1f} s")


def test_a_head_sent_a_byte_a_second_gets_408_at_the_header_timeout(server):
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        reply, seconds = _wait_for_answer(sock, b"GET /healthz HTTP/1.1\r\nhost: x\r\n\r\n")
    assert HEAD_S - 0.2 < seconds < HEAD_S + 1, seconds
    head, _, body = reply.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 408 ") and b"connection: close" in head.lower()
    assert "GRASP_HEADER_TIMEOUT_S" in json.loads(body)["detail"]
    with socket.create_connection(("127.0.0.1", server.port)) as sock:  # slow, but in time
        sock.sendall(b"GET /healthz HTTP/1.1\r\n")
        time.sleep(HEAD_S / 2)
        sock.sendall(b"host: x\r\n\r\n")
        assert sock.recv(4096).startswith(b"HTTP/1.1 200 ")


def test_a_body_sent_a_byte_a_second_is_cut_off_at_the_body_timeout(server):
    head = (f"POST /views HTTP/1.1\r\nhost: x\r\nauthorization: Bearer {TOKEN}\r\n"
            "content-type: application/json\r\ncontent-length: 1000\r\n\r\n").encode()  # fmt: skip
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        sock.sendall(head)
        reply, seconds = _wait_for_answer(sock, b" " * 1000)
    assert reply in (b"", None)  # disconnected, not answered
    assert BODY_S - 0.2 < seconds < BODY_S + 1, seconds
    assert httpx.get(f"{server.url}/healthz").status_code == 200
    log = server.log.read_text()
    assert "request body not complete in 3 s" in log
    assert "Exception in ASGI application" not in log  # the app ends the request quietly


def _get_healthz(sock: socket.socket) -> bytes:
    sock.sendall(b"GET /healthz HTTP/1.1\r\nhost: x\r\n\r\n")
    return sock.recv(4096)


def test_connections_over_the_cap_per_address_get_429_and_other_addresses_are_served(server):
    idle = [socket.create_connection(("127.0.0.1", server.port)) for _ in range(PER_CLIENT)]
    try:
        start = time.monotonic()
        with socket.create_connection(("127.0.0.1", server.port), timeout=HEAD_S) as extra:
            reply = extra.recv(4096)
            assert extra.recv(4096) == b""  # and closed
        assert time.monotonic() - start < 0.5
        head, _, body = reply.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 429 ") and b"retry-after: 1" in head.lower()
        assert "GRASP_MAX_CONNECTIONS_PER_CLIENT" in json.loads(body)["detail"]
        # 127.0.0.2 is another loopback address: another client, under its own cap
        with socket.create_connection(("127.0.0.1", server.port),
                                      source_address=("127.0.0.2", 0)) as other:  # fmt: skip
            assert _get_healthz(other).startswith(b"HTTP/1.1 200 ")
        assert _get_healthz(idle[0]).startswith(b"HTTP/1.1 200 ")  # the ones in are served
        idle.pop().close()  # a place frees up
        time.sleep(0.2)
        with socket.create_connection(("127.0.0.1", server.port)) as again:
            assert _get_healthz(again).startswith(b"HTTP/1.1 200 ")
        assert time.monotonic() - start < HEAD_S  # before the idle ones time out
    finally:
        for sock in idle:
            sock.close()


def test_an_over_long_url_gets_414_and_long_headers_431_readable_by_every_client(server):
    """A head over GRASP_MAX_HEAD_BYTES (16 KiB): JSON naming the limit, then a lingering close,
    so urllib and http.client read the answer instead of a reset (a 1 MB URL, a 200 KB header)."""
    url = f"{server.url}/grasp?session_id={'a' * MB}"
    with pytest.raises(urllib.error.HTTPError) as caught:
        urllib.request.urlopen(url, timeout=30)
    assert caught.value.code == 414
    assert "GRASP_MAX_HEAD_BYTES" in json.loads(caught.value.read())["detail"]
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
    try:
        conn.request("GET", "/healthz", headers={"x-padding": "b" * (200 * 1024)})
        r = conn.getresponse()
        detail = json.loads(r.read())["detail"]
        assert (r.status, r.getheader("connection")) == (431, "close")
        assert "headers are over 16384 bytes" in detail and "GRASP_MAX_HEAD_BYTES" in detail
    finally:
        conn.close()
    assert httpx.get(f"{server.url}/healthz").status_code == 200


@pytest.mark.parametrize(("where", "size", "status"), [
    ("url", 17 * 1024, 414), ("url", 100 * 1024, 414),
    ("header", 17 * 1024, 431), ("header", 100 * 1024, 431)])
def test_a_head_over_the_limit_in_one_write_is_refused(server, where, size, status):
    """GRASP_MAX_HEAD_BYTES holds however the head arrives: sent in one write, a 17 or 100 KB
    URL or header is refused as one sent in pieces is (h11 parses a complete head of any size);
    a head within the limit followed by its body in the same write is served."""
    line = f"GET /healthz?pad={'a' * size} HTTP/1.1" if where == "url" else "GET /healthz HTTP/1.1"
    extra = f"x-padding: {'b' * size}\r\n" if where == "header" else ""
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
        sock.sendall(f"{line}\r\nhost: x\r\n{extra}\r\n".encode())
        reply = b""
        while chunk := sock.recv(65536):
            reply += chunk
    head, _, body = reply.partition(b"\r\n\r\n")
    assert head.startswith(f"HTTP/1.1 {status} ".encode()), head[:100]
    assert "GRASP_MAX_HEAD_BYTES" in json.loads(body)["detail"]
    body = json.dumps(points_view()).encode()
    with socket.create_connection(("127.0.0.1", server.port), timeout=30) as sock:
        sock.sendall(b"POST /views HTTP/1.1\r\nhost: x\r\ncontent-type: application/json\r\n"
                     b"authorization: Bearer " + TOKEN.encode() + b"\r\nconnection: close\r\n"
                     b"content-length: " + str(len(body)).encode() + b"\r\n\r\n" + body)
        reply = b""
        while chunk := sock.recv(65536):
            reply += chunk
    assert reply.startswith(b"HTTP/1.1 200 "), reply[:200]


def test_refused_connections_are_logged_once_per_address_and_interval():
    from service.server.connections import RefusalLog

    now = [0.0]
    lines: list[str] = []
    log = RefusalLog(10.0, clock=lambda: now[0])
    for i in range(50_000):  # a client hammering: 5,000 refusals a second for 10 s
        now[0] = i / 5000
        log.refused("10.0.0.1", lambda m, *a: lines.append(m % a), "%s - refused", "10.0.0.1")
    log.refused("10.0.0.2", lambda m, *a: lines.append(m % a), "%s - refused", "10.0.0.2")
    now[0] = 10.5
    log.refused("10.0.0.1", lambda m, *a: lines.append(m % a), "%s - refused", "10.0.0.1")
    assert lines == ["10.0.0.1 - refused", "10.0.0.2 - refused",
                     "10.0.0.1 - refused (49999 more since the last line)"]


def test_a_flood_of_refused_connections_writes_a_line_or_two(server):
    idle = [socket.create_connection(("127.0.0.1", server.port)) for _ in range(PER_CLIENT)]
    try:
        for _ in range(300):
            with socket.create_connection(("127.0.0.1", server.port), timeout=HEAD_S) as extra:
                assert extra.recv(4096).startswith(b"HTTP/1.1 429 ")
    finally:
        for sock in idle:
            sock.close()
    time.sleep(0.2)
    lines = [line for line in server.log.read_text().splitlines()
             if "connections from this client" in line]
    assert 1 <= len(lines) <= 3, lines  # one per 10 s at most (an earlier test refused one too)


# ------------------------------------------------------------------ clients behind one address
TOKENS = ("alpha-token", "beta-token")


def test_a_client_is_named_by_its_token_or_the_address_a_trusted_proxy_forwards():
    from service.server.connections import Limits

    limits = Limits(1.0, 1.0, 4, 0, 16384, tokens=TOKENS, proxies=frozenset({"10.0.0.1"}))
    head = b"GET / HTTP/1.1\r\nHost: x\r\n"
    assert limits.keyed and not Limits(1.0, 1.0, 4, 0, 16384, tokens=TOKENS[:1]).keyed
    assert limits.client("10.0.0.7", head + b"Authorization: Bearer beta-token") == "token #2"
    assert limits.client("10.0.0.7", head + b"authorization: bearer  alpha-token ") == "token #1"
    assert limits.client("10.0.0.7", head + b"Authorization: Bearer gamma") == "10.0.0.7"
    # X-Forwarded-For only from a trusted proxy; the last address that is not one of them
    forwarded = head + b"X-Forwarded-For: 203.0.113.9, 198.51.100.4"
    assert limits.client("10.0.0.1", forwarded) == "198.51.100.4"
    assert limits.client("10.0.0.7", forwarded) == "10.0.0.7"
    assert limits.client("10.0.0.1", head + b"X-Forwarded-For: 198.51.100.4, 10.0.0.1") \
        == "198.51.100.4"
    assert limits.client("10.0.0.1", head + b"X-Forwarded-For: bogus") == "10.0.0.1"
    assert limits.client("10.0.0.1", head + b"X-Forwarded-For: 2001:DB8::1") == "2001:db8::1"
    assert limits.client("10.0.0.1", head) == "10.0.0.1"


@pytest.fixture(scope="module")
def nat_server(tmp_path_factory, tiny_model):
    """Two tokens and 127.0.0.1 as a trusted proxy: clients behind one address told apart."""
    tmp = tmp_path_factory.mktemp("nat")
    s = Server(tmp, tiny_model, tmp / "store.sqlite", token=",".join(TOKENS),
               trusted_proxies="127.0.0.1", header_timeout_s=20.0,
               max_connections_per_client=PER_CLIENT, planning_processes="false")
    yield s
    s.stop()


def _kept_open(port: int, source: str, headers: bytes) -> socket.socket:
    """A connection that made one request (GET /healthz) and stays open, as keep-alive ones do."""
    sock = socket.create_connection(("127.0.0.1", port), source_address=(source, 0))
    sock.sendall(b"GET /healthz HTTP/1.1\r\nhost: x\r\n" + headers + b"\r\n")
    assert sock.recv(4096).startswith(b"HTTP/1.1 200 ")
    return sock


def _one_request(port: int, source: str, headers: bytes) -> bytes:
    with socket.create_connection(("127.0.0.1", port), source_address=(source, 0),
                                  timeout=5) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nhost: x\r\n" + headers + b"\r\n")
        return sock.recv(4096)


def test_behind_one_address_each_token_has_its_own_cap(nat_server):
    """Issue 60, item 8: a client behind a NAT is not locked out by another one's connections:
    with several tokens each is a client. 4 connections of token 1 and 12 idle ones that never
    sent a head, all from 127.0.0.2: token 2 is served; token 1's fifth gets 429, and so does a
    tokenless one (its client is the address); 16 idle ones (4 × the cap) are the most an
    address may hold before heads name their clients."""
    port, src = nat_server.port, "127.0.0.2"
    alpha = b"authorization: Bearer alpha-token\r\n"
    held = [_kept_open(port, src, alpha) for _ in range(PER_CLIENT)]
    held += [socket.create_connection(("127.0.0.1", port), source_address=(src, 0))
             for _ in range(3 * PER_CLIENT)]
    try:
        time.sleep(0.2)
        assert _one_request(port, src, b"authorization: Bearer beta-token\r\n").startswith(
            b"HTTP/1.1 200 ")
        refused = _one_request(port, src, alpha)
        assert refused.startswith(b"HTTP/1.1 429 ")
        assert "more than 4 open connections from token #1" in json.loads(
            refused.partition(b"\r\n\r\n")[2])["detail"]
        # without a token of its own, a client is its address, which the idle ones fill
        assert _one_request(port, src, b"").startswith(b"HTTP/1.1 429 ")
        held += [socket.create_connection(("127.0.0.1", port), source_address=(src, 0))
                 for _ in range(PER_CLIENT)]  # 16 waiting for their head: 4 × the cap
        time.sleep(0.2)
        with socket.create_connection(("127.0.0.1", port), source_address=(src, 0),
                                      timeout=5) as flood:  # refused before it sends a byte
            assert flood.recv(4096).startswith(b"HTTP/1.1 429 ")
    finally:
        for sock in held:
            sock.close()


def test_behind_a_trusted_proxy_each_forwarded_address_has_its_own_cap(nat_server):
    port, src = nat_server.port, "127.0.0.1"  # the trusted proxy
    first = b"x-forwarded-for: 198.51.100.1\r\n"
    held = [_kept_open(port, src, first) for _ in range(PER_CLIENT)]
    try:
        time.sleep(0.2)
        refused = _one_request(port, src, first)
        assert refused.startswith(b"HTTP/1.1 429 ") and b"198.51.100.1" in refused
        assert _one_request(port, src, b"x-forwarded-for: 198.51.100.2\r\n").startswith(
            b"HTTP/1.1 200 ")
        # from an address that is not a trusted proxy the header is ignored
        assert _one_request(port, "127.0.0.3", first).startswith(b"HTTP/1.1 200 ")
    finally:
        for sock in held:
            sock.close()
