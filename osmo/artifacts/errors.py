"""The artifact store's exceptions; both derive from :class:`osmo.errors.OsmoError`.

::

    OsmoError
    ├── InfrastructureError
    │   └── ArtifactCorrupted   a blob does not match its digest, or is missing (exit 3)
    └── OutputRejected          an output folder holds something ingest refuses (exit 1)

Must not import anything beyond :mod:`osmo.errors`.
"""

from __future__ import annotations

from osmo.errors import InfrastructureError, OsmoError

__all__ = ["ArtifactCorrupted", "OutputRejected"]


class ArtifactCorrupted(InfrastructureError):
    """A blob's content no longer matches its digest, or the blob is missing (exit code 3).

    Attributes:
        digest: the digest the blob was stored under (``"sha256:<hex>"``).
        path: where the blob lives (or should live) in the store.
        actual: the digest of the content found, or ``None`` when the blob is missing.
    """

    exit_code = 3

    def __init__(self, digest: str, path: str, actual: str | None) -> None:
        self.digest = digest
        self.path = path
        self.actual = actual
        found = "is missing" if actual is None else f"now hashes to {actual}"
        super().__init__(
            f"artifact blob {digest} at {path} {found}; it was not used. Re-run the task that "
            "produced it (delete the blob first if it exists, so the next ingest stores it again)")


class OutputRejected(OsmoError):
    """An output folder holds something that cannot be stored as an artifact (exit code 1).

    Attributes:
        path: the offending entry, relative to the output folder ("": the whole output).
        reason: what is wrong with it and how to fix it.
    """

    exit_code = 1

    def __init__(self, path: str, reason: str) -> None:
        self.path = path
        self.reason = reason
        super().__init__(f"output {path!r} {reason}" if path else f"the output {reason}")
