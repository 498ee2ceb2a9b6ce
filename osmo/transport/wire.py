"""What the server and a remote worker say to each other: keys and JSON messages.

The server's side is ``osmo.server.workers.WorkerHub``, the worker's
``osmo.worker.remote.RemoteWorker``; both speak only through this module's functions.

Keys, under the cluster prefix ``osmo/<cluster>``:

- ``alive/server`` and ``alive/worker/<id>`` — liveliness tokens. A worker's token going
  away (process killed, network cut: noticed within the 1 s lease) is its ``NodeDown``; the
  server's token coming back tells a worker to register again.
- ``api/worker_register`` — a worker's hello (see :func:`hello`), answered with the server's
  host id and artifact folder (a worker on the same host links blobs instead of fetching).
- ``to-worker/<id>`` — the server's orders: ``prepare`` (the attempt, the task's workflow
  spec the first time, input manifests, secrets, ``max_output_bytes``: the task's storage
  limit), ``run``, ``kill``, ``ack`` (an exit report
  was received and its outputs are safe on the server), ``drain`` notices.
- ``from-worker/<id>`` — the worker's reports: ``prepared``, ``started``, ``exited``,
  ``start_failed``, ``lost`` (handed back while draining); ``from-worker/<id>/log`` carries
  log records (attachment: the attempt id), appended by the server to its copy of the log.

Attempt ids fence everything: a report about an attempt the scheduler has superseded is
ignored, so a worker that returns late can never commit stale work.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

from osmo.scheduler.types import (
    AttemptExited,
    AttemptLost,
    AttemptPrepared,
    AttemptStarted,
    AttemptStartFailed,
    Capacity,
    Event,
    PrepareAttempt,
)
from osmo.errors import UsageError
from osmo.names import shown
from osmo.spec.model import WorkflowSpec
from osmo.transport.rpc import MAX_INT, field

__all__ = ["capacity_from_dict", "capacity_to_dict", "event_from_dict", "event_to_dict",
           "prepare_from_dict", "prepare_to_dict", "spec_from_wire", "spec_to_wire"]


def event_to_dict(event: Event) -> dict[str, Any]:
    """A worker's report as JSON-safe data."""
    if isinstance(event, AttemptPrepared):
        return {"op": "prepared", "attempt_id": event.attempt_id}
    if isinstance(event, AttemptStarted):
        return {"op": "started", "attempt_id": event.attempt_id}
    if isinstance(event, AttemptStartFailed):
        return {"op": "start_failed", "attempt_id": event.attempt_id, "message": event.message}
    if isinstance(event, AttemptLost):
        return {"op": "lost", "attempt_id": event.attempt_id, "message": event.message}
    if isinstance(event, AttemptExited):
        out = asdict(event)
        out["op"] = "exited"
        return out
    raise TypeError(f"not a worker report: {event!r}")


def event_from_dict(data: dict[str, Any]) -> Event:
    """The inverse of :func:`event_to_dict`.

    Raises:
        ValueError: an unknown ``op``.
    """
    op, aid = data.get("op"), str(data.get("attempt_id"))
    if op == "prepared":
        return AttemptPrepared(aid)
    if op == "started":
        return AttemptStarted(aid)
    if op == "start_failed":
        return AttemptStartFailed(aid, str(data.get("message", "")))
    if op == "lost":
        return AttemptLost(aid, str(data.get("message", "worker lost")))
    if op == "exited":
        command = data.get("command")
        return AttemptExited(aid, int(data["exit_code"]), data.get("output"),
                             str(data.get("message") or ""), data.get("manifest"),
                             bool(data.get("cached")),
                             tuple(command) if command is not None else None)
    raise ValueError(f"unknown report {op!r}")


def prepare_to_dict(cmd: PrepareAttempt) -> dict[str, Any]:
    """A placement as JSON-safe data."""
    return asdict(cmd)


def prepare_from_dict(data: dict[str, Any]) -> PrepareAttempt:
    """The inverse of :func:`prepare_to_dict`."""
    return PrepareAttempt(
        attempt_id=str(data["attempt_id"]), workflow_id=str(data["workflow_id"]),
        task=str(data["task"]), retry=int(data["retry"]), node_id=str(data["node_id"]),
        inputs={str(k): str(v) for k, v in data["inputs"].items()},
        hosts={str(k): str(v) for k, v in data["hosts"].items()}, run=bool(data["run"]))


def capacity_to_dict(capacity: Capacity) -> dict[str, Any]:
    """A worker's capacity as it advertises it."""
    return {"cpu": capacity.cpu, "gpu": capacity.gpu, "memory": capacity.memory,
            "storage": capacity.storage}


def capacity_from_dict(data: dict[str, Any]) -> Capacity:
    """The inverse of :func:`capacity_to_dict`; absent amounts are zero.

    Raises:
        UsageError: an amount that is not a number of the right kind, or is negative.
    """
    cpu = data.get("cpu", 0)
    if isinstance(cpu, bool) or not isinstance(cpu, int | float) or not 0 <= cpu <= MAX_INT:
        raise UsageError(f"'capacity.cpu' must be a number from 0, not {shown(cpu)}")
    amounts = {key: field(data, key, int, default=0, what=f"'capacity.{key}'")
               for key in ("gpu", "memory", "storage")}
    negative = [key for key, value in amounts.items() if value < 0]
    if negative:
        raise UsageError(f"'capacity.{negative[0]}' must not be negative")
    return Capacity(cpu=float(cpu), **amounts)


def spec_to_wire(spec: dict[str, Any], filename: str, types: dict[str, Any]) -> dict[str, Any]:
    """A stored workflow spec (its dict form), its file name and resolved task types."""
    return {"spec": spec, "filename": filename, "types": types}


def spec_from_wire(data: dict[str, Any]) -> WorkflowSpec:
    """The spec a worker runs tasks from (task types as the server resolved them)."""
    from osmo.spec import spec_from_dict
    from osmo.spec.model import ResolvedType
    from osmo.spec.typed import apply_resolved

    spec = spec_from_dict(data["spec"], filename=data.get("filename") or "<submitted>")
    return apply_resolved(spec, {name: ResolvedType.from_dict(t)
                                 for name, t in (data.get("types") or {}).items()})
