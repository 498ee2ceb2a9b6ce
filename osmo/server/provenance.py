"""Builds the lineage of a completed attempt from what the engine knows when it exits.

Called on the engine thread for an ``AttemptExited`` that carries an output manifest and is
the task's current attempt (a stale report never gets lineage). The result is written in
the same transaction as the status change that completes the task.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

from osmo.artifacts import Manifest
from osmo.record import Lineage, LineageInput
from osmo.scheduler.types import AttemptExited, PrepareAttempt
from osmo.spec.model import TaskSpec
from osmo.store.sqlite import LineageRow
from osmo.version import __version__

__all__ = ["Provenance"]


@dataclass
class _Placed:
    """What the engine remembers of an attempt between its placement and its exit."""

    cmd: PrepareAttempt
    node_address: str
    fingerprint: str | None
    inputs: tuple[LineageInput, ...]
    image_id: str | None = None


@dataclass
class Provenance:
    """Remembers placements (inputs, node) and turns exits into lineage rows."""

    _placed: dict[str, _Placed] = field(default_factory=dict)

    def placed(self, cmd: PrepareAttempt, node_address: str, fingerprint: str | None = None,
               inputs: list[LineageInput | None] | None = None, *,
               image_id: str | None = None) -> None:
        """Note an attempt's node, cache fingerprint and recorded inputs when it is placed.

        ``image_id``: the image id its fingerprint was made with (the worker's must match).
        """
        known = tuple(i for i in inputs or () if i is not None)
        self._placed[cmd.attempt_id] = _Placed(cmd, node_address, fingerprint, known, image_id)

    def exited(self, event: AttemptExited, task: TaskSpec, *, started_at: float | None,
               now: float) -> LineageRow | None:
        """The lineage row of a successful exit with outputs, else None.

        The placement is kept until :meth:`forget`: the engine forgets it once the exit is
        committed, so a batch that failed and is applied again still finds it.
        """
        placed = self._placed.get(event.attempt_id)
        if event.manifest is None or event.output is None or placed is None:
            return None
        manifest = Manifest.from_json(event.manifest)
        record = Lineage(
            workflow_id=placed.cmd.workflow_id, task=placed.cmd.task, retry=placed.cmd.retry,
            attempt_id=event.attempt_id, node=placed.node_address,
            command=None if task.type else (
                event.command or (tuple(task.command) + tuple(task.args) or None)),
            plugin=_plugin(task), params=dict(task.params), image=task.image,
            image_id=event.image_id,
            inputs=placed.inputs,
            started_at=started_at, ended_at=now, exit_code=event.exit_code,
            manifest_digest=manifest.digest, osmo_version=__version__)
        return LineageRow(
            attempt_id=event.attempt_id, workflow_id=placed.cmd.workflow_id,
            task=placed.cmd.task, manifest=manifest.digest, manifest_body=event.manifest,
            entries=tuple((e.path, e.digest, e.size) for e in manifest.entries),
            output_path=event.output, record=json.dumps(record.to_dict()),
            consumed=tuple(i.manifest_digest for i in record.inputs),
            fingerprint=None if event.cached or _other_image(placed, event) else placed.fingerprint)

    def forget(self, attempt_id: str) -> None:
        """Drop what was remembered of an attempt whose final report was committed."""
        self._placed.pop(attempt_id, None)


def _other_image(placed: _Placed, event: AttemptExited) -> bool:
    """Whether the attempt ran another image than its fingerprint names (moved meanwhile)."""
    return placed.image_id is not None and event.image_id != placed.image_id


def _plugin(task: TaskSpec) -> str | None:
    """``type@version`` of a typed task (``type`` alone if its version is unknown)."""
    if task.type is None:
        return None
    return f"{task.type}@{task.resolved.version}" if task.resolved else task.type
