"""Connection-level guards of ``python -m service``: read deadlines, a cap per client,
and early answers that every client can read.

uvicorn (h11) has a keep-alive timeout and a global cap (``limit_concurrency``), but no deadline
for a request's head or body, no cap per address, and it closes a connection right after an
answer sent before the body was read (a 401 from ``TokenGate``, a 413 from ``BodyLimit``): the
unread body makes the kernel send RST, and a client that reads only after sending (urllib,
http.client, requests) gets ConnectionResetError instead of the answer. None of this is a uvicorn
option, so :class:`GuardedH11Protocol` subclasses its h11 protocol (picked with
``uvicorn.Config(http=...)``) and adds, per connection:

- a **head deadline**: the request line and headers arrive within ``header_timeout_s`` of the
  connection opening or of the previous answer, else 408 (when part of a head came) and close;
- a **body deadline**: the body arrives within ``body_timeout_s`` of its head, else close;
- a **cap per client**: a connection beyond ``max_per_client`` open ones of its client gets 429
  and is closed; other clients are served. A client is its address; when the server can tell
  clients apart behind one address (``GRASP_TOKEN`` lists several tokens, or
  ``GRASP_TRUSTED_PROXIES`` names proxies), a connection is counted under the client its first
  request's head names, its token or the address its proxy forwards, as nginx's ``limit_conn``
  keyed by a header counts requests once their head is read. Until then it counts under its
  address, where up to :data:`PENDING_PER_ADDRESS` × the cap may wait, so that 64 slow
  connections from a NAT do not lock out the clients behind it;
- a **lingering close** after an early answer, as nginx's ``lingering_close`` and Apache's
  lingering close do: the answer is followed by FIN, then the rest of the body is read and
  discarded (at most ``max_drain_bytes``, within the body deadline) before the socket closes.
  On a keep-alive connection uvicorn itself discards the rest and reads the next request; the
  same bounds apply.

Hand-written because neither uvicorn nor Starlette offers these; a reverse proxy in front does
(nginx: ``client_header_timeout``, ``client_body_timeout``, ``limit_conn``, ``lingering_close``),
but ``python -m service`` is also run on its own. It leans on uvicorn's H11Protocol internals
(``conn``, ``flow``, ``_unset_keepalive_if_required``): :func:`serve` refuses to start on a
uvicorn outside :data:`TESTED_UVICORN` (the minor releases tests/test_connections.py passed
on), and pyproject.toml's range admits only those.

A connection is in one phase at a time, read off h11's states after every event: ``head``
(waiting for a request), ``body`` (reading one), ``app`` (the app has the request: no deadline,
a grasp plan may take long) or ``linger`` (answered; discarding input until the socket closes).
"""

from __future__ import annotations

import asyncio
import ipaddress
import json
import math
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any, Literal

import h11
from uvicorn.config import Config
from uvicorn.protocols.http.h11_impl import STATUS_PHRASES, H11Protocol
from uvicorn.server import ServerState

from service.api.auth import token_index
from service.settings import Settings

#: Seconds a refused connection stays open after its 429, discarding what the client sends, so
#: a client that sends its request before reading sees the 429 and not a reset.
REFUSED_LINGER_S = 1.0

#: Refused connections are logged once per client and interval (seconds), with counts.
REFUSED_LOG_INTERVAL_S = 10.0

#: A server that keys clients by token or forwarded address lets this many times the cap of
#: connections wait for their first head from one address (bounding a flood of idle ones).
PENDING_PER_ADDRESS = 4

Phase = Literal["head", "body", "app", "linger"]
_ANSWERED = (h11.DONE, h11.MUST_CLOSE, h11.CLOSED)  # h11 states of a server whose answer is out


@dataclass(frozen=True)
class Limits:
    """What :class:`GuardedH11Protocol` enforces (from the ``GRASP_*`` settings)."""

    header_timeout_s: float
    body_timeout_s: float
    max_per_client: int
    max_drain_bytes: int  # read and discarded after an early answer, at most
    max_head_bytes: int  # the request line and headers together, at most
    tokens: tuple[str, ...] = ()  # GRASP_TOKEN's: with two or more, each is a client
    proxies: frozenset[str] = frozenset()  # GRASP_TRUSTED_PROXIES

    @classmethod
    def of(cls, settings: Settings) -> Limits:
        """An over-limit body of up to twice GRASP_MAX_BODY_BYTES still gets a readable 413."""
        return cls(
            header_timeout_s=settings.header_timeout_s,
            body_timeout_s=settings.body_timeout_s,
            max_per_client=settings.max_connections_per_client,
            max_drain_bytes=2 * settings.max_body_bytes,
            max_head_bytes=settings.max_head_bytes,
            tokens=settings.tokens(),
            proxies=settings.proxies(),
        )

    @property
    def keyed(self) -> bool:
        """Whether a request's head may name a client other than its connection's address."""
        return len(self.tokens) > 1 or bool(self.proxies)

    def client(self, address: str, head: bytes) -> str:
        """The client a request ``head`` (line and headers) from ``address`` names: ``token
        #i`` when it carries the i-th of several tokens, else the address a trusted proxy
        forwards (X-Forwarded-For's last one that is not a proxy), else ``address``."""
        headers: dict[bytes, bytes] = {}
        for line in head.split(b"\r\n")[1:]:
            name, _, value = line.partition(b":")
            headers[name.strip().lower()] = value.strip()  # the last of a repeated header
        if len(self.tokens) > 1:
            i = token_index(headers.get(b"authorization"), self.tokens)
            if i is not None:
                return f"token #{i + 1}"
        if address in self.proxies and b"x-forwarded-for" in headers:
            for hop in reversed(headers[b"x-forwarded-for"].decode("latin-1").split(",")):
                try:
                    hop = str(ipaddress.ip_address(hop.strip()))
                except ValueError:
                    break  # not an address: believe nothing further left
                if hop not in self.proxies:
                    return hop
        return address


#: The uvicorn minor releases this module's use of H11Protocol internals was tested with.
TESTED_UVICORN = ("0.54",)


class RefusalLog:
    """One log line per client per ``interval_s`` for refused connections, however many
    there were: the first refusal is logged at once, the rest of the interval is counted and
    told on the next line ("… 5123 more since the last line")."""

    def __init__(self, interval_s: float = REFUSED_LOG_INTERVAL_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.interval_s, self.clock = interval_s, clock
        self.last: dict[str, float] = {}  # address → when its last line was written
        self.unlogged: Counter[str] = Counter()

    def refused(self, address: str, log: Callable[..., None], message: str, *args: object) -> None:
        now = self.clock()
        if now - self.last.get(address, -math.inf) < self.interval_s:
            self.unlogged[address] += 1
            return
        more = self.unlogged.pop(address, 0)
        self.last[address] = now
        for stale in [a for a, t in self.last.items() if now - t > 6 * self.interval_s]:
            del self.last[stale]  # addresses quiet for a while: forget them
        suffix = f" ({more} more since the last line)" if more else ""
        log(message + suffix, *args)


def check_uvicorn(version: str) -> None:
    """``SystemExit`` with what to do when ``version`` is not a tested uvicorn release."""
    if ".".join(version.split(".")[:2]) not in TESTED_UVICORN:
        raise SystemExit(
            f"python -m service: uvicorn {version} is installed, but the connection guards "
            f"(service/server/connections.py) use uvicorn's H11Protocol internals and were tested "
            f"with uvicorn {', '.join(v + '.x' for v in TESTED_UVICORN)} only; install the locked "
            "set (pip install -c requirements.lock -e .) or test that release and add it to "
            "TESTED_UVICORN")


def serve(app: Callable, settings: Settings) -> None:
    """``uvicorn.run`` on ``settings.host:port``, each connection a :class:`GuardedH11Protocol`;
    refuses an untested uvicorn (:func:`check_uvicorn`)."""
    import uvicorn

    check_uvicorn(uvicorn.__version__)
    # uvicorn calls Config.http as a factory (config=, server_state=, app_state=, _loop=), so a
    # partial carries the limits and the count of connections per address that all share.
    protocol = partial(GuardedH11Protocol, limits=Limits.of(settings), per_client=Counter(),
                       refusals=RefusalLog())
    proxies = settings.proxies()  # X-Forwarded-For is believed from these alone (off: none)
    uvicorn.run(app, host=settings.host, port=settings.port, log_level="info", http=protocol,
                h11_max_incomplete_event_size=settings.max_head_bytes,
                proxy_headers=bool(proxies), forwarded_allow_ips=",".join(sorted(proxies)) or None)


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with the deadlines, cap and lingering close of this module."""

    def __init__(
        self,
        config: Config,
        server_state: ServerState,
        app_state: dict[str, Any],
        _loop: asyncio.AbstractEventLoop | None = None,
        *,
        limits: Limits,
        per_client: Counter[str],
        refusals: RefusalLog | None = None,
    ) -> None:
        super().__init__(config, server_state, app_state, _loop)
        self.limits = limits
        self.per_client = per_client  # open connections by client host, shared by all
        self.refusals = refusals or RefusalLog()  # shared by all, in serve()
        self.address: str | None = None
        self.key: str | None = None  # the client it counts under: its address, then (keyed)
        self.named = False  # whether a request head has named its client yet
        self.socket: asyncio.Transport = None  # type: ignore[assignment]  # uvicorn's wraps it
        self.phase: Phase | None = None
        self.deadline: asyncio.TimerHandle | None = None
        self.body_due = 0.0  # loop time by which the body must have arrived
        self.drain_left = 0  # bytes still to discard after an early answer
        self.drain_framed = False  # linger until h11 sees the end of the body, not just EOF

    # ------------------------------------------------------------------ asyncio.Protocol
    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        self.socket = transport
        super().connection_made(_GentleClose(transport, self))  # type: ignore[arg-type]
        if self.client is not None:
            self.address = self.client[0]
            self._count_under(self.address)
            waiting = PENDING_PER_ADDRESS if self.limits.keyed else 1
            if self.per_client[self.address] > waiting * self.limits.max_per_client:
                self._refuse()
                return
        self._watch()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        self._count_under(None)
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self.phase == "linger":
            self._discard(data)
            return
        if self._answered_early() and self._over_drain(len(data)):
            return  # else uvicorn discards the rest of the body and reads the next request
        if self.phase == "head" and self._head_over_limit(data):
            return
        if self.phase == "head" and not self.named and self.limits.keyed and self._named(data):
            return
        super().data_received(data)
        self._watch()

    # ------------------------------------------------------------------ uvicorn's hooks
    def on_response_complete(self) -> None:
        super().on_response_complete()
        self.drain_left = self.limits.max_drain_bytes  # if answered early (data_received)
        self._watch()

    def shutdown(self) -> None:
        if self.phase == "linger":
            self.socket.close()
        else:
            super().shutdown()

    def close_gently(self) -> None:
        """uvicorn closes the connection: first drain a body the client is still sending."""
        if self.phase == "linger" or self.socket.is_closing():
            self.socket.close()
        elif self._answered_early():
            self._linger(until=self.body_due, framed=True)
        else:
            self.socket.close()

    def send_400_response(self, msg: str) -> None:
        """uvicorn's plain-text 400 for a head h11 cannot parse. A head over h11's size limit
        (``max_head_bytes``) gets a JSON answer naming the limit instead: 414 when the request
        line alone is over it, else 431; then a lingering close, so that a client still sending
        the head reads the answer rather than a reset."""
        received, _ = self.conn.trailing_data
        if len(received) <= self.limits.max_head_bytes:
            super().send_400_response(msg)
            return
        self._answer(*self._head_refusal(received))
        self._linger(until=self.loop.time() + self.limits.header_timeout_s, framed=False)

    def _head_over_limit(self, data: bytes) -> bool:
        """Refuse a head over ``max_head_bytes`` however it arrives: h11 stops an incomplete
        head at that size (:meth:`send_400_response`) but parses a complete one of any size, so
        a 100 KB URL sent in one write got through. True when refused (answered, lingering)."""
        received, _ = self.conn.trailing_data
        limit = self.limits.max_head_bytes
        if len(received) + len(data) <= limit:
            return False
        head = received + data
        end = head.find(b"\r\n\r\n")
        if 0 <= end <= limit - 4:
            return False  # a head within the limit, and the start of a body or the next request
        status, detail = self._head_refusal(head)
        body = json.dumps({"detail": detail}).encode()  # raw: h11 has seen no request to answer
        headers = [*self.server_state.default_headers, (b"content-type", b"application/json"),
                   (b"content-length", str(len(body)).encode()), (b"connection", b"close")]
        lines = [b"HTTP/1.1 %d %s" % (status, STATUS_PHRASES[status]),
                 *(name + b": " + value for name, value in headers)]
        self.socket.write(b"\r\n".join(lines) + b"\r\n\r\n" + body)
        self._linger(until=self.loop.time() + self.limits.header_timeout_s, framed=False)
        return True

    def _named(self, data: bytes) -> bool:
        """Once the first request's head is complete, count the connection under the client it
        names (:meth:`Limits.client`); True when that client is over the cap (429 sent)."""
        received, _ = self.conn.trailing_data
        head = received + data
        end = head.find(b"\r\n\r\n")
        if end < 0 or self.address is None:
            return False
        self.named = True
        self._count_under(self.limits.client(self.address, head[:end]))
        if self.per_client[self.key] > self.limits.max_per_client:
            self._refuse()
            return True
        return False

    def _count_under(self, key: str | None) -> None:
        """Move this connection's count from its current client to ``key`` (None: gone)."""
        if self.key is not None:
            self.per_client[self.key] -= 1
            if self.per_client[self.key] <= 0:
                del self.per_client[self.key]
        self.key = key
        if key is not None:
            self.per_client[key] += 1

    def _head_refusal(self, head: bytes) -> tuple[int, str]:
        """414 when the request line alone is over the limit, else 431, with what to do."""
        limit = self.limits.max_head_bytes
        line_end = head.find(b"\r\n")
        if line_end < 0 or line_end > limit:
            return 414, (f"the request line (method, URL, version) is over {limit} bytes "
                         "(GRASP_MAX_HEAD_BYTES): send data in the body")
        return 431, (f"the request line and headers are over {limit} bytes together "
                     "(GRASP_MAX_HEAD_BYTES)")

    def _answered_early(self) -> bool:
        """The answer is out while the client is still sending the request body."""
        return self.conn.their_state is h11.SEND_BODY and self.conn.our_state in _ANSWERED

    # ------------------------------------------------------------------ phases
    def _watch(self) -> None:
        """Arm the deadline of the phase h11's states now say the connection is in."""
        if self.phase == "linger" or self.socket.is_closing():
            return
        their = self.conn.their_state
        phase: Phase = "head" if their is h11.IDLE else "body" if their is h11.SEND_BODY else "app"
        if phase == self.phase:
            return
        self.phase = phase
        now = self.loop.time()
        if phase == "head":
            self._arm(now + self.limits.header_timeout_s, self._head_late)
        elif phase == "body":
            self.body_due = now + self.limits.body_timeout_s
            self._arm(self.body_due, self._body_late)
        else:
            self._disarm()

    def _head_late(self) -> None:
        received, _ = self.conn.trailing_data  # the part of a head that came, if any
        if received:
            self._log("request head not complete in %g s: 408", self.limits.header_timeout_s)
            self._answer(
                408,
                f"the request line and headers did not arrive within "
                f"{self.limits.header_timeout_s:g} s (GRASP_HEADER_TIMEOUT_S)",
            )
        self.socket.close()

    def _body_late(self) -> None:
        self._log("request body not complete in %g s: disconnected", self.limits.body_timeout_s)
        self.socket.close()  # the app's receive() sees http.disconnect

    def _refuse(self) -> None:
        n, who = self.limits.max_per_client, self.key
        if who == self.address and self.limits.keyed and not self.named:
            n *= PENDING_PER_ADDRESS  # connections from one address still sending their head
        self.refusals.refused(who, self.logger.warning,
                              "%s - over %d connections from this client: 429", who, n)
        self._answer(
            429,
            f"more than {n} open connections from {who} "
            "(GRASP_MAX_CONNECTIONS_PER_CLIENT): close some or reuse them",
            retry_after="1",
        )
        self._linger(until=self.loop.time() + REFUSED_LINGER_S, framed=False)

    # ------------------------------------------------------------------ lingering close
    def _linger(self, *, until: float, framed: bool) -> None:
        """After an answer: FIN, then discard input until EOF, the end of the body (when
        ``framed``), ``max_drain_bytes`` or ``until``, whichever first; then close."""
        self.phase = "linger"
        self._unset_keepalive_if_required()
        self.drain_left = self.limits.max_drain_bytes
        self.drain_framed = framed
        self._arm(until, self.socket.close)
        if self.socket.can_write_eof():
            self.socket.write_eof()  # the client's next read ends after the answer
        self.flow.resume_reading()  # uvicorn pauses reading while the app has not read

    def _over_drain(self, n: int) -> bool:
        """Count ``n`` more bytes discarded after an answer; past the bound, close."""
        self.drain_left -= n
        if self.drain_left >= 0:
            return False
        self._log("over %d bytes sent after the answer: closed", self.limits.max_drain_bytes)
        self.socket.close()
        return True

    def _discard(self, data: bytes) -> None:
        if self._over_drain(len(data)) or not self.drain_framed:
            return
        try:
            self.conn.receive_data(data)
            while True:
                event = self.conn.next_event()
                if event is h11.NEED_DATA or event is h11.PAUSED:
                    return
                if isinstance(event, (h11.EndOfMessage, h11.ConnectionClosed)):
                    break
        except h11.RemoteProtocolError:
            pass
        self.socket.close()  # the whole body read: nothing unread, so FIN and no reset

    # ------------------------------------------------------------------ helpers
    def _arm(self, when: float, callback: Callable[[], None]) -> None:
        self._disarm()
        self.deadline = self.loop.call_at(when, callback)

    def _disarm(self) -> None:
        if self.deadline is not None:
            self.deadline.cancel()
            self.deadline = None

    def _answer(self, status: int, detail: str, *, retry_after: str | None = None) -> None:
        """A JSON ``{"detail": ...}`` answer with Connection: close, outside any ASGI cycle."""
        body = json.dumps({"detail": detail}).encode()
        headers = [
            *self.server_state.default_headers,
            (b"content-type", b"application/json"),
            (b"content-length", str(len(body)).encode()),
            (b"connection", b"close"),
        ]
        if retry_after is not None:
            headers.append((b"retry-after", retry_after.encode()))
        events = [
            h11.Response(status_code=status, headers=headers, reason=STATUS_PHRASES[status]),
            h11.Data(data=body),
            h11.EndOfMessage(),
        ]
        self.socket.write(b"".join(self.conn.send(event) or b"" for event in events))

    def _log(self, message: str, *args: object) -> None:
        prefix = f"{self.client[0]}:{self.client[1]} - " if self.client else ""
        self.logger.info(prefix + message, *args)


class _GentleClose:
    """The socket's transport as uvicorn sees it, but ``close()`` lets the protocol drain a body
    the client is still sending first. uvicorn's RequestResponseCycle closes the transport it was
    given right after an answer with Connection: close, so wrapping the transport is the one
    place to step in without copying uvicorn's request loop."""

    def __init__(self, transport: asyncio.Transport, protocol: GuardedH11Protocol) -> None:
        self._transport = transport
        self._protocol = protocol

    def close(self) -> None:
        self._protocol.close_gently()

    def is_closing(self) -> bool:
        return self._protocol.phase == "linger" or self._transport.is_closing()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._transport, name)
