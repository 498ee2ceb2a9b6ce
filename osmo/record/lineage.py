"""Lineage: who made an attempt's outputs, from what, with what, and when.

Owns the :class:`Lineage` record and its three encodings: a JSON-safe dict (``to_dict``; used
for the ``/osmo/lineage`` channel of a run record and by the store), a flat string map
(``to_metadata``; the MCAP metadata record ``osmo.lineage`` that travels inside an MCAP file
written through the SDK), and the environment a task sees (``from_env``).

This module is pure data: it must not import ``mcap``, touch files, or know about the server.
"""

from __future__ import annotations

import json
import math
import os
import socket
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from osmo.errors import UsageError

__all__ = ["LINEAGE_METADATA", "LINEAGE_VERSION", "Lineage", "LineageInput"]

LINEAGE_METADATA = "osmo.lineage"
"""Name of the MCAP metadata record that carries a file's lineage."""

LINEAGE_VERSION = "1"
"""Format version written as the ``lineage_version`` key of the metadata record."""

# Flat-map encoding, per field: plain strings stay raw (readable in Foxglove/rerun), optional
# strings are omitted when None (so "" and None stay distinct), everything else is JSON.
_STR_FIELDS = ("workflow_id", "task", "node", "osmo_version")
_OPT_STR_FIELDS = ("attempt_id", "plugin", "image", "image_id", "manifest_digest")
_JSON_FIELDS = (
    "retry", "command", "params", "inputs", "started_at", "ended_at", "exit_code",
)


@dataclass(frozen=True)
class LineageInput:
    """One input an attempt consumed: the upstream task's output manifest.

    Attributes:
        task: the upstream task's name.
        workflow_id: the workflow the upstream task ran in (may differ when inputs are reused).
        manifest_digest: ``sha256:...`` digest of the upstream attempt's output manifest.
    """

    task: str
    workflow_id: str
    manifest_digest: str

    def to_dict(self) -> dict[str, str]:
        """Return ``{"task", "workflow_id", "manifest"}``, the JSON form."""
        return {"task": self.task, "workflow_id": self.workflow_id,
                "manifest": self.manifest_digest}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> LineageInput:
        """Build from the JSON form (``manifest`` or ``manifest_digest`` accepted).

        Raises:
            UsageError: a key is missing or not a string.
        """
        digest = data.get("manifest", data.get("manifest_digest"))
        values = (data.get("task"), data.get("workflow_id"), digest)
        if not all(isinstance(v, str) for v in values):
            raise UsageError(
                f"lineage input {dict(data)!r} needs string 'task', 'workflow_id', 'manifest'"
            )
        return cls(*values)  # type: ignore[arg-type]


@dataclass(frozen=True)
class Lineage:
    """Provenance of one attempt of one task.

    A partial record (from :meth:`from_env`, inside a running task) leaves unknown fields at
    their defaults; the server's complete record fills every field it knows.

    Attributes:
        workflow_id: the workflow's id.
        task: the task's name.
        retry: the retry number (0 for the first run).
        attempt_id: the attempt's unique id, None when unknown.
        node: the node (worker address or host) the attempt ran on ("" when unknown).
        command: the argv the task ran, None for plugin tasks or when unknown.
        plugin: ``"type@version"`` for plugin tasks, else None.
        params: the task's resolved plugin parameters (JSON-safe).
        image: the container image, None when run without one.
        image_id: the id (``sha256:...``) the image resolved to when the task ran in it,
            None when it ran as a process.
        inputs: the upstream manifests the attempt consumed.
        started_at: start time (unix seconds), None when unknown.
        ended_at: end time (unix seconds), None when unknown or still running.
        exit_code: the process exit code, None when unknown or still running.
        manifest_digest: ``sha256:...`` of the attempt's output manifest, None when none yet.
        osmo_version: the osmo version that recorded this lineage.
    """

    workflow_id: str
    task: str
    retry: int = 0
    attempt_id: str | None = None
    node: str = ""
    command: tuple[str, ...] | None = None
    plugin: str | None = None
    params: dict[str, Any] = field(default_factory=dict, hash=False)
    image: str | None = None
    inputs: tuple[LineageInput, ...] = ()
    image_id: str | None = None
    started_at: float | None = None
    ended_at: float | None = None
    exit_code: int | None = None
    manifest_digest: str | None = None
    osmo_version: str = field(default_factory=lambda: _osmo_version())

    # ------------------------------------------------------------------ JSON dict form

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-safe dict (tuples become lists, inputs become dicts)."""
        return {
            "workflow_id": self.workflow_id,
            "task": self.task,
            "retry": self.retry,
            "attempt_id": self.attempt_id,
            "node": self.node,
            "command": list(self.command) if self.command is not None else None,
            "plugin": self.plugin,
            "params": dict(self.params),
            "image": self.image,
            "image_id": self.image_id,
            "inputs": [i.to_dict() for i in self.inputs],
            "started_at": self.started_at,
            "ended_at": self.ended_at,
            "exit_code": self.exit_code,
            "manifest_digest": self.manifest_digest,
            "osmo_version": self.osmo_version,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Lineage:
        """Build from :meth:`to_dict` output; unknown keys are ignored (newer writers).

        Raises:
            UsageError: a required key is missing or a value has the wrong type.
        """
        try:
            record = cls(
                workflow_id=_typed(data, "workflow_id", str),
                task=_typed(data, "task", str),
                retry=_typed(data, "retry", int, default=0),
                attempt_id=_typed(data, "attempt_id", str, optional=True),
                node=_typed(data, "node", str, default=""),
                command=_command(data.get("command")),
                plugin=_typed(data, "plugin", str, optional=True),
                params=dict(_typed(data, "params", dict, default={})),
                image=_typed(data, "image", str, optional=True),
                image_id=_typed(data, "image_id", str, optional=True),
                inputs=tuple(LineageInput.from_dict(i)
                             for i in _typed(data, "inputs", list, default=[])),
                started_at=_time(data, "started_at"),
                ended_at=_time(data, "ended_at"),
                exit_code=_typed(data, "exit_code", int, optional=True),
                manifest_digest=_typed(data, "manifest_digest", str, optional=True),
                osmo_version=_typed(data, "osmo_version", str, default=""),
            )
        except AttributeError as exc:  # a list or string where an object belongs
            raise UsageError(f"lineage record is malformed: {exc}") from exc
        return record

    # ------------------------------------------------------------------ metadata form

    def to_metadata(self) -> dict[str, str]:
        """Return the flat string map of the ``osmo.lineage`` MCAP metadata record.

        Plain strings are stored raw, optional strings are omitted when None, and every other
        value (numbers, lists, objects, None) is JSON-encoded.
        """
        data = self.to_dict()
        out = {"lineage_version": LINEAGE_VERSION}
        out.update({k: data[k] for k in _STR_FIELDS})
        out.update({k: data[k] for k in _OPT_STR_FIELDS if data[k] is not None})
        out.update({k: _json(data[k]) for k in _JSON_FIELDS})
        return out

    @classmethod
    def from_metadata(cls, data: Mapping[str, str]) -> Lineage:
        """Inverse of :meth:`to_metadata`.

        Raises:
            UsageError: a key is missing or a JSON value does not parse.
        """
        decoded: dict[str, Any] = {k: data[k] for k in _STR_FIELDS + _OPT_STR_FIELDS if k in data}
        for key in _JSON_FIELDS:
            if key in data:
                try:
                    decoded[key] = json.loads(data[key])
                except (TypeError, ValueError) as exc:
                    raise UsageError(f"lineage metadata key {key!r} is not JSON: {exc}") from exc
        return cls.from_dict(decoded)

    # ------------------------------------------------------------------ environment form

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None) -> Lineage:
        """Build a partial lineage from the variables osmo sets for a running task.

        Required: ``OSMO_WORKFLOW_ID``, ``OSMO_TASK``, ``OSMO_RETRY``. Optional, when the worker
        provides them: ``OSMO_ATTEMPT_ID``, ``OSMO_NODE`` (default: this host's name),
        ``OSMO_PLUGIN``, ``OSMO_IMAGE``, ``OSMO_STARTED_AT`` (unix seconds), and the JSON values
        ``OSMO_COMMAND`` (list), ``OSMO_PARAMS`` (object), ``OSMO_INPUTS`` (list of
        ``{"task", "workflow_id", "manifest"}``).

        Args:
            env: the environment to read (default: ``os.environ``).

        Raises:
            UsageError: not inside an osmo task (a required variable is missing) or a variable
                does not parse.
        """
        env = os.environ if env is None else env
        missing = [k for k in ("OSMO_WORKFLOW_ID", "OSMO_TASK", "OSMO_RETRY") if not env.get(k)]
        if missing:
            raise UsageError(
                f"{', '.join(missing)} not set: Lineage.from_env() works inside an osmo task; "
                "elsewhere build Lineage(...) yourself or pass lineage=None"
            )
        data: dict[str, Any] = {
            "workflow_id": env["OSMO_WORKFLOW_ID"],
            "task": env["OSMO_TASK"],
            "retry": _env_json(env, "OSMO_RETRY"),
            "attempt_id": env.get("OSMO_ATTEMPT_ID") or None,
            "node": env.get("OSMO_NODE") or socket.gethostname(),
            "plugin": env.get("OSMO_PLUGIN") or None,
            "image": env.get("OSMO_IMAGE") or None,
            "started_at": _env_json(env, "OSMO_STARTED_AT"),
            "command": _env_json(env, "OSMO_COMMAND"),
            "params": _env_json(env, "OSMO_PARAMS") or {},
            "inputs": _env_json(env, "OSMO_INPUTS") or [],
            "osmo_version": _osmo_version(),
        }
        return cls.from_dict(data)


def _osmo_version() -> str:
    """The running osmo's version (imported late: ``osmo/__init__`` is lazy and cheap)."""
    from osmo.version import __version__

    return __version__


def _json(value: Any) -> str:
    return compact_json(value, f"lineage value {value!r}")


def compact_json(value: Any, what: str = "value") -> str:
    r"""Compact JSON text that is valid UTF-8, with no NaN (Foxglove and browsers reject it).

    Non-ASCII text is kept as it is, except when a string holds a byte that is not UTF-8
    (a file name; see ``osmo.artifacts.manifest``): the whole text is then written with
    ``\u`` escapes, which every JSON reader accepts and Python reads back exactly.

    Raises:
        UsageError: the value is not JSON-serialisable; ``what`` names it in the message.
    """
    try:
        text = json.dumps(value, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise UsageError(f"{what} is not JSON-serialisable: {exc}") from exc
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return json.dumps(value, separators=(",", ":"), ensure_ascii=True, allow_nan=False)
    return text


def _typed(data: Mapping[str, Any], key: str, kind: type, *, default: Any = None,
           optional: bool = False) -> Any:
    """Return ``data[key]`` checked against ``kind`` (bool is never an int here).

    A missing key or None gives ``default`` (None when ``optional``); a key with neither
    a default nor ``optional`` is required.
    """
    value = data.get(key)
    if value is None:
        if optional or default is not None:
            return default
        raise UsageError(f"lineage record is missing {key!r}")
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise UsageError(
            f"lineage {key!r} must be {kind.__name__}, got {type(value).__name__} {value!r}"
        )
    return value


def _time(data: Mapping[str, Any], key: str) -> float | None:
    """A finite unix time in seconds, or None."""
    value = data.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise UsageError(f"lineage {key!r} must be unix seconds, got {value!r}")
    return float(value)


def _command(value: Any) -> tuple[str, ...] | None:
    """The argv as a tuple of strings, or None."""
    if value is None:
        return None
    if not isinstance(value, list | tuple) or not all(isinstance(a, str) for a in value):
        raise UsageError(f"lineage 'command' must be a list of strings, got {value!r}")
    return tuple(value)


def _env_json(env: Mapping[str, str], name: str) -> Any:
    """Parse a JSON-valued variable; None when unset or empty."""
    raw = env.get(name)
    if not raw:
        return None
    try:
        return json.loads(raw)
    except ValueError as exc:
        raise UsageError(f"{name}={raw!r} is not valid JSON: {exc}") from exc
