"""Where sessions live: the interface (``base``), SQLite (``sqlite_store``, the embedded default),
Redis (``redis_store``, shared by replicas), and the store the settings name with the session
locks (``sessions``)."""
