"""The Python SDK: ``osmo.Client`` and what it stands on.

``client`` is the client, ``connect`` finds, starts and stops a local server, ``transfer``
moves files to and from a server as blobs.
"""
