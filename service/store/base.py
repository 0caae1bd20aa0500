"""The session store interface: what the pipeline uses, whichever engine keeps the sessions.

Two engines implement :class:`Store` (docs/design.md §9):
:class:`service.store.sqlite_store.SQLiteSessionStore` keeps sessions in one SQLite file (the
embedded default) and :class:`service.store.redis_store.RedisSessionStore` keeps them in Redis so
that several replicas share them (``GRASP_STORE_URL``); :func:`service.store.sessions.open_store`
picks one from the settings.

A session holds the whole ``CompletionStream`` state (model memory, current grid, latest logits,
counters: a few hundred kB, constant in the number of views), so a server killed at any moment
and restarted on the same store continues every stream exactly.

Writes are compare-and-swap on the view count, so two writers (threads, processes or replicas)
can never both apply their view on top of the same state.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from service.settings import MAX_ANSWERS


class SessionNotFound(LookupError):
    """No such session (never made, deleted, or expired)."""


class StoreFull(RuntimeError):
    """The store holds ``max_sessions`` live sessions."""


class ConcurrentUpdate(RuntimeError):
    """Another writer applied a view first; reload and try again."""


#: Seconds a session's lock across replicas lives unless its holder renews it (the default of
#: ``GRASP_LOCK_LEASE_S``): a replica that dies holding it blocks that session this long at most.
LEASE_S = 5.0
#: A view waits for its session's lock at most this many leases (then the answer is 503): one
#: lease lets a dead holder's lock expire, the second one covers views queued on other replicas.
WAIT_LEASES = 2.0
#: Seconds between two tries of a waiting view.
POLL_S = 0.05


class NoLease:
    """The hold on a session of a store that one process owns (SQLite): nothing to take. Views
    of a session queue in :class:`service.store.sessions.SessionLocks`; the CAS guards the rest."""

    def release(self) -> None:
        pass


@dataclass(frozen=True)
class SessionRecord:
    id: str
    model: str  # fingerprint of the model that made the state
    created: float  # unix seconds
    updated: float
    views: int
    object_seen: bool
    state: bytes  # CompletionStream.to_bytes()
    owner: str = ""  # the client that made it (service.store.owned.client_id); "" without tokens


@dataclass(frozen=True)
class KeptAnswer:
    """What an ``Idempotency-Key`` keeps: the first answer (JSON text), the SHA-256 of the request
    body that got it, and the session it belongs to (deleted with it)."""

    answer: str
    digest: str
    session_id: str


class Store:
    """What every session store does; thread-safe. Subclasses implement the storage."""

    clock: Callable[[], float]

    def __init__(self, *, max_sessions: int, ttl_s: float, unseen_ttl_s: float | None,
                 max_answers: int = MAX_ANSWERS) -> None:
        self.max_sessions = max_sessions
        self.max_answers = max_answers  # idempotent answers kept per client, the oldest out
        self.ttl_s = ttl_s
        # a session that never saw an object lives this long (it cannot answer anything yet)
        self.unseen_ttl_s = ttl_s if unseen_ttl_s is None else min(unseen_ttl_s, ttl_s)

    @property
    def where(self) -> str:
        """Where the sessions live, for the log."""
        raise NotImplementedError

    def get(self, session_id: str) -> SessionRecord:
        """The live session; raises SessionNotFound."""
        raise NotImplementedError

    def count(self) -> int:
        """Live sessions."""
        raise NotImplementedError

    def create(
        self, session_id: str, *, model: str, state: bytes, views: int, object_seen: bool,
        owner: str = "",
    ) -> SessionRecord:
        """Insert a new session of ``owner``; raises StoreFull when ``max_sessions`` are live."""
        raise NotImplementedError

    def update(
        self, record: SessionRecord, *, state: bytes, views: int, object_seen: bool
    ) -> SessionRecord:
        """Replace the state of ``record`` if nobody changed it since it was read.

        Raises ConcurrentUpdate when another writer got there first, SessionNotFound when the
        session was deleted meanwhile.
        """
        raise NotImplementedError

    def delete(self, session_id: str) -> bool:
        """Delete a session and the idempotent answers that belong to it; False when there was
        none."""
        raise NotImplementedError

    def purge_expired(self) -> int:
        """Delete every expired session; returns how many."""
        raise NotImplementedError

    def recall(self, key: str) -> KeptAnswer | None:
        """What an idempotency key keeps, None if nothing (never seen, expired, its session
        deleted, or pushed out by ``max_answers`` newer ones of its owner)."""
        raise NotImplementedError

    def remember(self, key: str, kept: KeptAnswer, *, owner: str = "") -> None:
        """Keep ``kept`` under the idempotency ``key`` for ``ttl_s`` (a session's life) or until
        its session is deleted; ``owner`` keeps at most ``max_answers``, the oldest dropped."""
        raise NotImplementedError

    def try_lock(self, session_id: str, *, lease_s: float = LEASE_S):
        """The session's lock across processes if it is free now, None while another holds it;
        never waits. Held until its ``release()``. A store one process owns has nothing to lock
        (:class:`NoLease`); a shared one overrides this."""
        return NoLease()

    @contextmanager
    def exclusive(self, session_id: str) -> Iterator[None]:
        """Held while one view is applied to the session. The compare-and-swap of
        :meth:`update` is what guarantees order; a store shared by several processes also
        queues them here so that none has to retry."""
        yield

    def close(self) -> None:
        """Release connections."""

    def ensure_room(self) -> None:
        """Raise StoreFull when no new session fits (a cheap check before doing any work)."""
        if self.count() >= self.max_sessions:
            raise self._full()

    def _full(self) -> StoreFull:
        return StoreFull(
            f"the session store is full ({self.max_sessions} sessions): DELETE finished sessions, "
            f"or retry once idle ones expire ({self.ttl_s:g} s after their last view)"
        )

    def ttl_of(self, record: SessionRecord) -> float:
        """Seconds after its last view that ``record`` expires."""
        return self.ttl_s if record.object_seen else self.unseen_ttl_s

    def not_found_message(self, session_id: str) -> str:
        return (
            f"unknown session {session_id!r}: it does not exist, was deleted, or expired after "
            f"{self.ttl_s:g} s without a view ({self.unseen_ttl_s:g} s while no view had shown "
            "the object); POST /views without session_id starts a new one"
        )
