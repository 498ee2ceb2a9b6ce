"""Artifacts: a content-addressed blob store and the per-attempt manifests that index it.

Every file a task outputs is hashed (sha256) into :class:`ArtifactStore`; an attempt's
:class:`Manifest` lists each file's (path, digest, size). This package owns the blobs on disk
and the manifest format; it must not import the scheduler, the state store or anything above
them (lineage and references are recorded by callers).
"""

from __future__ import annotations

from osmo.artifacts.errors import ArtifactCorrupted, OutputRejected
from osmo.artifacts.manifest import Entry, Manifest
from osmo.artifacts.store import DEFAULT_GRACE, ArtifactStore

__all__ = [
    "DEFAULT_GRACE",
    "ArtifactCorrupted",
    "ArtifactStore",
    "Entry",
    "Manifest",
    "OutputRejected",
]
