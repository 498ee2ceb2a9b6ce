"""The server: one process per ``OSMO_HOME`` (``app.serve``).

It composes the state store, the scheduler, the engine and its executors (the local pool,
the remote-worker hub) and the zenoh API (``handlers``, one function per verb). The engine
(``engine``) is the only writer of the store; the rest of this package serves it: typed
requests (``requests``, ``inbox``), recovery and fault isolation (``recovery``,
``isolation``), placement, caching and provenance (``placing``, ``cache``, ``provenance``),
datasets, credentials, lineage queries, logs and run records.
"""
