"""Datasets: named, versioned sets of files made by tasks (or uploaded) and read by tasks.

- ``outputs: - dataset: {name, path?, regex?, metadata?}`` makes a new version of ``name``
  when the task completes: the files of its output under ``path`` (re-rooted there) that
  match ``regex``. Versions count up from 1 per name and share blobs with the output.
- ``inputs: - dataset: {name: NAME[:TAG_OR_VERSION], regex?}`` gives the task that version
  (default: the newest) as a read-only folder, resolved when the task is placed. A dataset
  made by an earlier task of the same workflow is only seen if that task finished first:
  a dataset input is not a dependency edge (use ``- task:`` for that).
- Each version's folder is materialized once, verified, under
  ``OSMO_HOME/datasets/<name>/<version>[-<regex digest>]`` and reused by every reader. It is
  registered as an output so caching and lineage see its manifest like any task output.
"""

from __future__ import annotations

import hashlib
import re
import shutil
import uuid
from dataclasses import replace
from pathlib import Path
from typing import Any

from osmo.artifacts import ArtifactStore, Entry, Manifest
from osmo.errors import NotFoundError
from osmo.layout import Home
from osmo.names import parse_ref
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import TaskSpec
from osmo.store.sqlite import DatasetRow, Store

__all__ = ["Datasets", "select"]


def select(manifest: Manifest, *, path: str | None, regex: str | None) -> Manifest:
    """The entries of ``manifest`` under ``path`` (re-rooted) whose path matches ``regex``."""
    prefix = path.strip("/") + "/" if path and path.strip("/") else ""
    pattern = re.compile(regex) if regex else None
    chosen = []
    for e in manifest.entries:
        if prefix and not e.path.startswith(prefix):
            continue
        rel = e.path[len(prefix):]
        if pattern is None or pattern.search(rel):
            chosen.append(Entry(rel, e.digest, e.size))
    return Manifest(tuple(chosen))


class Datasets:
    """Makes dataset versions and resolves dataset inputs (engine thread only)."""

    def __init__(self, store: Store, artifacts: ArtifactStore, home: Home) -> None:
        self._store = store
        self._artifacts = artifacts
        self._home = home
        self._versions: dict[str, int] = {}

    def next_version(self, name: str) -> int:
        """Allocate the next version number of ``name``."""
        version = max(self._versions.get(name, 0), self._store.next_dataset_version(name) - 1)
        self._versions[name] = version + 1
        return version + 1

    def versions_made(self, task: TaskSpec, manifest: Manifest, attempt_id: str | None,
                      now: float) -> list[DatasetRow]:
        """New versions for every ``dataset`` output of a task that produced ``manifest``."""
        rows = []
        for out in task.outputs:
            if out.dataset is None:
                continue
            rows.append(self.version_row(out.dataset, select(manifest, path=out.path,
                                                            regex=out.regex),
                                         source=manifest.digest, attempt_id=attempt_id,
                                         now=now, metadata=out.metadata or {}))
        return rows

    def version_row(self, name: str, manifest: Manifest, *, source: str | None,
                    attempt_id: str | None, now: float, metadata: dict[str, Any]) -> DatasetRow:
        """A new version of ``name`` holding ``manifest``."""
        return DatasetRow(
            name=name, version=self.next_version(name), manifest=manifest.digest,
            manifest_body=manifest.to_json(),
            entries=tuple((e.path, e.digest, e.size) for e in manifest.entries),
            source_manifest=source, attempt_id=attempt_id, created_at=now, metadata=metadata)

    def resolve_inputs(self, cmd: PrepareAttempt, task: TaskSpec) -> PrepareAttempt:
        """``cmd`` with a folder for each dataset and other-workflow input, resolved now.

        Keyed as written in the spec.

        Raises:
            NotFoundError: a named dataset, version or other-workflow output does not exist.
        """
        extra: dict[str, str] = {}
        for spec in task.inputs:
            if spec.dataset is not None:
                extra[spec.dataset] = str(self.folder(spec.dataset, spec.regex))
            elif spec.workflow is not None and spec.task is not None:
                extra[f"{spec.workflow}:{spec.task}"] = self._other_workflow(spec.workflow,
                                                                             spec.task)
        return replace(cmd, inputs={**cmd.inputs, **extra}) if extra else cmd

    def _other_workflow(self, workflow_id: str, task: str) -> str:
        """The promoted output folder of ``task`` in another workflow (``- task: WF:NAME``)."""
        outputs = self._store.outputs(workflow_id, task)
        if not outputs:
            raise NotFoundError(f"workflow '{workflow_id}' has no completed output for task "
                                f"'{task}'")
        return str(outputs[0]["path"])

    def folder(self, ref: str, regex: str | None) -> Path:
        """The materialized, registered folder of dataset ``NAME[:TAG_OR_VERSION]``.

        Raises:
            UsageError: ``ref`` is not a valid reference (checked before it names a folder).
            NotFoundError: no such dataset or version.
        """
        name, tag = parse_ref(ref)
        row = self._store.dataset(name, tag)
        if row is None:
            known = [f"{d['name']}:{d['version']}" for d in self._store.datasets(name)][:5]
            hint = f" (known: {', '.join(known)})" if known else " (no versions yet)"
            raise NotFoundError(f"dataset '{ref}' does not exist{hint}")
        body = self._store.manifest_body(row["manifest"])
        assert body is not None
        manifest = select(Manifest.from_json(body), path=None, regex=regex)
        variant = hashlib.sha256(regex.encode()).hexdigest()[:12] if regex else None
        target = self._home.dataset_version(name, row["version"], variant)
        if not target.is_dir():
            self._materialize(manifest, target, f"dataset:{name}")
        return target

    def _materialize(self, manifest: Manifest, target: Path, owner: str) -> None:
        """Write the folder once, verified, and register it.

        It is registered (so caching and lineage see its manifest) before it appears under its final
        name.
        """
        staging = target.parent / f".{target.name}.{uuid.uuid4().hex}"
        staging.mkdir(parents=True)
        try:
            self._artifacts.materialize(manifest, staging)
            self._store.register_output(
                owner, target.name, manifest.digest, manifest.to_json(),
                tuple((e.path, e.digest, e.size) for e in manifest.entries), str(target))
            staging.rename(target)
        finally:
            if staging.exists():
                shutil.rmtree(staging, ignore_errors=True)
