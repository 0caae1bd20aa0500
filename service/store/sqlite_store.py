"""The SQLite session store, the embedded default: :class:`SQLiteSessionStore` implements the
:class:`service.store.base.Store` interface on one SQLite file (one row per session), in WAL mode,
so a committed view survives a killed process. Writes are compare-and-swap on the view count (see
:mod:`service.store.base`). :mod:`service.store.redis_store` is the other implementation;
:func:`service.store.sessions.open_store` picks one from the settings.
"""

from __future__ import annotations

import logging
import sqlite3
import time
from collections.abc import Callable
from contextlib import closing
from pathlib import Path

from service.store.base import (
    MAX_ANSWERS,
    ConcurrentUpdate,
    KeptAnswer,
    SessionNotFound,
    SessionRecord,
    Store,
)

log = logging.getLogger(__name__)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS sessions (
    id TEXT PRIMARY KEY,
    model TEXT NOT NULL,
    created REAL NOT NULL,
    updated REAL NOT NULL,
    views INTEGER NOT NULL,
    object_seen INTEGER NOT NULL,
    state BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS answers (
    key TEXT PRIMARY KEY,
    answer TEXT NOT NULL,
    expires REAL NOT NULL
);
"""

#: Columns added since the first schema: a file written before them gains them when opened.
_ADDED = (
    ("sessions", "owner", "TEXT NOT NULL DEFAULT ''"),
    ("answers", "digest", "TEXT NOT NULL DEFAULT ''"),
    ("answers", "session", "TEXT NOT NULL DEFAULT ''"),
    ("answers", "owner", "TEXT NOT NULL DEFAULT ''"),
)

_INDEXES = """
CREATE INDEX IF NOT EXISTS sessions_updated ON sessions (updated);
CREATE INDEX IF NOT EXISTS answers_session ON answers (session);
CREATE INDEX IF NOT EXISTS answers_owner ON answers (owner, expires);
"""


#: SQL condition of an expired session, with the two limits of :meth:`SQLiteSessionStore._limits`.
_EXPIRED = "((object_seen = 1 AND updated < ?) OR (object_seen = 0 AND updated < ?))"


class SQLiteSessionStore(Store):
    """Sessions in one SQLite file; safe to use from many threads (a connection per call)."""

    def __init__(
        self,
        path: str | Path,
        *,
        max_sessions: int,
        ttl_s: float,
        unseen_ttl_s: float | None = None,
        max_answers: int = MAX_ANSWERS,
        clock: Callable[[], float] = time.time,
    ) -> None:
        super().__init__(max_sessions=max_sessions, ttl_s=ttl_s, unseen_ttl_s=unseen_ttl_s,
                         max_answers=max_answers)
        self.path = Path(path)
        self.clock = clock
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with closing(self._connect()) as con:
            con.execute("PRAGMA auto_vacuum=INCREMENTAL")  # lets purges give the space back
            con.execute("PRAGMA journal_mode=WAL")
            con.executescript(_SCHEMA)
            for table, column, declared in _ADDED:
                if column not in {row[1] for row in con.execute(f"PRAGMA table_info({table})")}:
                    con.execute(f"ALTER TABLE {table} ADD COLUMN {column} {declared}")
            con.executescript(_INDEXES)

    @property
    def where(self) -> str:
        return str(self.path)

    def _connect(self) -> sqlite3.Connection:
        con = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
        con.execute("PRAGMA synchronous=NORMAL")  # WAL: durable against a killed process
        return con

    # ---------------------------------------------------------------------------- reads
    def get(self, session_id: str) -> SessionRecord:
        """The live session; raises SessionNotFound (an expired one is deleted on the way)."""
        with closing(self._connect()) as con:
            row = con.execute(
                "SELECT id, model, created, updated, views, object_seen, state, owner "
                "FROM sessions WHERE id = ?",
                (session_id,),
            ).fetchone()
            if row is None:
                raise SessionNotFound(self.not_found_message(session_id))
            record = SessionRecord(*row[:5], bool(row[5]), bytes(row[6]), row[7])
            if self._expired(record.updated, record.object_seen):
                con.execute(
                    "DELETE FROM sessions WHERE id = ? AND updated = ?",
                    (session_id, record.updated),
                )
                raise SessionNotFound(self.not_found_message(session_id))
        return record

    def count(self) -> int:
        with closing(self._connect()) as con:
            query = f"SELECT COUNT(*) FROM sessions WHERE NOT {_EXPIRED}"
            (n,) = con.execute(query, self._limits()).fetchone()
        return int(n)

    def _expired(self, updated: float, object_seen: bool) -> bool:
        return updated < self.clock() - (self.ttl_s if object_seen else self.unseen_ttl_s)

    def _limits(self) -> tuple[float, float]:
        """The oldest ``updated`` still alive: for seen, then for unseen sessions."""
        now = self.clock()
        return now - self.ttl_s, now - self.unseen_ttl_s

    # ---------------------------------------------------------------------------- writes
    def create(
        self, session_id: str, *, model: str, state: bytes, views: int, object_seen: bool,
        owner: str = "",
    ) -> SessionRecord:
        now = self.clock()
        with closing(self._connect()) as con:
            con.execute("BEGIN IMMEDIATE")
            try:
                con.execute(f"DELETE FROM sessions WHERE {_EXPIRED}", self._limits())
                (n,) = con.execute("SELECT COUNT(*) FROM sessions").fetchone()
                if n >= self.max_sessions:
                    raise self._full()
                con.execute(
                    "INSERT INTO sessions (id, model, created, updated, views, object_seen, state,"
                    " owner) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                    (session_id, model, now, now, views, int(object_seen), state, owner),
                )
                con.execute("COMMIT")
            except BaseException:
                con.execute("ROLLBACK")
                raise
        return SessionRecord(session_id, model, now, now, views, object_seen, state, owner)

    def update(
        self, record: SessionRecord, *, state: bytes, views: int, object_seen: bool
    ) -> SessionRecord:
        now = self.clock()
        with closing(self._connect()) as con:
            cursor = con.execute(
                "UPDATE sessions SET state = ?, views = ?, object_seen = ?, updated = ? "
                "WHERE id = ? AND views = ?",
                (state, views, int(object_seen), now, record.id, record.views),
            )
            if cursor.rowcount == 0:
                exists = con.execute("SELECT 1 FROM sessions WHERE id = ?", (record.id,)).fetchone()
                if exists is None:
                    raise SessionNotFound(self.not_found_message(record.id))
                raise ConcurrentUpdate(f"session {record.id!r} changed while a view was applied")
        return SessionRecord(
            record.id, record.model, record.created, now, views, object_seen, state, record.owner
        )

    def delete(self, session_id: str) -> bool:
        with closing(self._connect()) as con:
            cursor = con.execute("DELETE FROM sessions WHERE id = ?", (session_id,))
            con.execute("DELETE FROM answers WHERE session = ?", (session_id,))
            con.executescript("PRAGMA incremental_vacuum;")  # (executescript steps it to the end)
        return cursor.rowcount > 0

    def recall(self, key: str) -> KeptAnswer | None:
        with closing(self._connect()) as con:
            row = con.execute("SELECT answer, digest, session FROM answers "
                              "WHERE key = ? AND expires > ?", (key, self.clock())).fetchone()
        return None if row is None else KeptAnswer(*map(str, row))

    def remember(self, key: str, kept: KeptAnswer, *, owner: str = "") -> None:
        with closing(self._connect()) as con:
            con.execute("BEGIN IMMEDIATE")
            try:
                con.execute("INSERT OR REPLACE INTO answers (key, answer, expires, digest, "
                            "session, owner) VALUES (?, ?, ?, ?, ?, ?)",
                            (key, kept.answer, self.clock() + self.ttl_s, kept.digest,
                             kept.session_id, owner))
                (n,) = con.execute("SELECT COUNT(*) FROM answers WHERE owner = ?",
                                   (owner,)).fetchone()
                if n > self.max_answers:  # the owner's oldest go
                    con.execute("DELETE FROM answers WHERE key IN (SELECT key FROM answers "
                                "WHERE owner = ? ORDER BY expires LIMIT ?)",
                                (owner, n - self.max_answers))
                con.execute("COMMIT")
            except BaseException:
                con.execute("ROLLBACK")
                raise

    def purge_expired(self) -> int:
        with closing(self._connect()) as con:
            con.execute("DELETE FROM answers WHERE expires <= ?", (self.clock(),))
            cursor = con.execute(f"DELETE FROM sessions WHERE {_EXPIRED}", self._limits())
            con.executescript("PRAGMA incremental_vacuum;")  # the file shrinks back
        if cursor.rowcount:
            log.info("purged %d expired sessions", cursor.rowcount)
        return cursor.rowcount
