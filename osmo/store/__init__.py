"""The state store: one SQLite file under ``OSMO_HOME``.

``sqlite`` is the only module that imports ``sqlite3``; ``rows`` and ``writes`` are what it
reads and writes, ``lineage`` its lineage queries.
"""
