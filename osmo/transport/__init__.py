"""Zenoh transport: how the server, its workers and its clients talk.

``zenoh_link`` is the only module that imports zenoh; ``rpc`` is the API's request/reply,
``blobs`` moves artifact blobs by digest, ``wire`` holds the server-worker messages.
"""
