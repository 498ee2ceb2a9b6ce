"""Plain records the store reads and writes (frozen dataclasses; no database access here).

A workflow's spec and submission are records of their own (``osmo.spec.stored``,
``osmo.store.submission``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from osmo.spec.stored import StoredSpec
from osmo.store.submission import Submission

__all__ = ["AttemptRow", "DatasetRow", "LineageRow", "NewWorkflowRow", "TagRow", "WorkflowRow"]


@dataclass(frozen=True)
class WorkflowRow:
    """A stored workflow: its state payload, its spec and how it was submitted."""

    id: str
    name: str
    status: str
    submitted_at: float
    spec: StoredSpec
    options: Submission
    state: dict[str, Any]


@dataclass(frozen=True)
class NewWorkflowRow:
    """A workflow to create: its id ``name-n``, submit time, spec and submission."""

    id: str
    name: str
    n: int
    submitted_at: float
    spec: StoredSpec
    options: Submission


@dataclass(frozen=True)
class TagRow:
    """Dataset ``name``'s ``tag`` pointing at ``version``."""

    name: str
    tag: str
    version: int


@dataclass(frozen=True)
class AttemptRow:
    """Where an attempt ran and, for local attempts, which process to clean up after a crash."""

    id: str
    workflow_id: str
    task: str
    retry: int
    node_id: str | None
    dir: str | None
    pid: int | None
    pid_start: float | None


@dataclass(frozen=True)
class LineageRow:
    """What one successful attempt made and used, written with the batch that completes it.

    Attributes:
        manifest: digest of the attempt's output manifest; ``manifest_body`` its JSON.
        entries: ``(path, blob digest, size)`` of every file in the manifest.
        output_path: the promoted output folder (how downstream tasks receive it).
        record: the lineage record as JSON (``osmo.record.Lineage.to_dict``).
        consumed: manifest digests of the inputs it read.
    """

    attempt_id: str
    workflow_id: str
    task: str
    manifest: str
    manifest_body: str
    entries: tuple[tuple[str, str, int], ...]
    output_path: str
    record: str
    consumed: tuple[str, ...]
    fingerprint: str | None = None  # set when the attempt may serve as a cache entry


@dataclass(frozen=True)
class DatasetRow:
    """A new dataset version: its manifest (written too) and where it came from."""

    name: str
    version: int
    manifest: str
    manifest_body: str
    entries: tuple[tuple[str, str, int], ...]
    source_manifest: str | None
    attempt_id: str | None
    created_at: float
    metadata: dict[str, Any]
