"""Sessions that belong to a client: :class:`OwnedStore` is the store as one client sees it.

A client is its bearer token (:func:`client_id`: a hash of it, so that the store never holds a
token), or nobody (``""``) when the service runs without ``GRASP_TOKEN``. A session belongs to the
client that created it: every other client is told it does not exist (404, the answer an unknown
id gets, so that a guessed id learns nothing), whichever route it tries. Idempotency keys are the
client's own too: the same key sent by two clients names two answers.

With one token or none every request is the same client, so nothing changes for a single robot.
A session made under one token is not seen under another, also while tokens are rotated.
"""

from __future__ import annotations

import hashlib

from service.store.base import KeptAnswer, SessionNotFound, SessionRecord, Store


def client_id(token: str | None) -> str:
    """Who a request is, as stored with its sessions: a hash of its token ("" without one)."""
    if token is None:
        return ""
    return hashlib.sha256(token.encode()).hexdigest()[:32]


class OwnedStore:
    """``store`` as the client ``owner`` sees it: its own sessions and its own idempotent
    answers; everything else (counts, locks, limits) is the store's."""

    def __init__(self, store: Store, owner: str) -> None:
        self.store = store
        self.owner = owner

    def __getattr__(self, name: str):
        return getattr(self.store, name)

    def get(self, session_id: str) -> SessionRecord:
        """The session if it is this client's; SessionNotFound otherwise, as for no session."""
        record = self.store.get(session_id)
        if record.owner != self.owner:
            raise SessionNotFound(self.store.not_found_message(session_id))
        return record

    def create(self, session_id: str, **fields) -> SessionRecord:
        return self.store.create(session_id, owner=self.owner, **fields)

    def delete(self, session_id: str) -> bool:
        """Delete the session if it is this client's (an owner never changes, so checking first
        is enough); False when there is none to this client."""
        try:
            self.get(session_id)
        except SessionNotFound:
            return False
        return self.store.delete(session_id)

    def recall(self, key: str) -> KeptAnswer | None:
        return self.store.recall(self._scoped(key))

    def remember(self, key: str, kept: KeptAnswer) -> None:
        self.store.remember(self._scoped(key), kept, owner=self.owner)

    def _scoped(self, key: str) -> str:
        return f"{self.owner}/{key}"  # an owner is hex: no "/" in it, so no two pairs collide
