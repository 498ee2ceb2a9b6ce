r"""Moving a folder to and from a URL (task ``inputs:``/``outputs:`` ``url:`` entries).

Owns the public surface of the URL adapters: :func:`for_url` picks a :class:`Remote` for a URL
(``file://``, ``s3://``), whose ``upload``/``download`` move a folder as a whole and never leave
a partial result that looks complete (see :mod:`osmo.urls.base` for the marker protocol).
Must not import a scheme's module until a URL names it, nor any third-party library.

Example::

    from osmo.urls import for_url
    remote = for_url("s3://bucket/run-7", {"endpoint": "http://127.0.0.1:9000",
                                           "access_key": "...", "secret_key": "..."})
    remote.upload(Path("out"), regex=r"\.mcap$")
    remote.download(Path("in"))
"""

from __future__ import annotations

from osmo.urls.base import MARKER, Remote, UrlError, for_url

__all__ = ["MARKER", "Remote", "UrlError", "for_url"]
