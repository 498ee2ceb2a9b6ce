"""The run record: one MCAP file per finished workflow that Foxglove and rerun open directly.

Layout, record version 2 (a message's log time is its event's time in ns since the unix
epoch; every channel's log times are in order)::

    /osmo/log      foxglove.Log (protobuf, Foxglove's own schema), what the Log panel shows:
                   one per task output line   name = task, file = "<task>/<retry>/<stream>",
                                              line = its line number in that stream, level
                                              INFO (stdout) or WARNING (stderr)
                   one per status transition  name = task (the workflow id for the workflow's
                                              own), file empty, level ERROR for a FAILED*
                                              status, WARNING for RESCHEDULED, else INFO
    /osmo/status   one message per status transition  (JSON, osmo.StatusTransition)
    /osmo/lineage  one message per attempt             (JSON, osmo.Lineage, Lineage.to_dict())
    metadata "osmo.workflow": id, name, status, submitted_at, ended_at (strings), record_version,
                              and "workflow": the whole workflow dict as JSON

Version 1 records (log lines as JSON ``osmo.LogLine`` on ``/osmo/logs``) still read.

This module owns that layout and nothing else: it builds messages from plain dicts the server
already has and leaves the MCAP encoding to :mod:`osmo.record.mcapio` and the protobuf to
:mod:`osmo.record.foxlog`. It must not import ``mcap``, protobuf or the server.
"""

from __future__ import annotations

import enum
import heapq
import json
import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from osmo.errors import UsageError
from osmo.record.foxlog import LOG_SCHEMA, LogEntry, encode_log, log_decoder, log_schema
from osmo.record.lineage import Lineage, compact_json
from osmo.record.mcapio import JsonMcapWriter, McapFile, McapMessage, RecordError

__all__ = [
    "LINEAGE_TOPIC",
    "LOG_TOPIC",
    "LOGS_TOPIC",
    "RECORD_VERSION",
    "STATUS_TOPIC",
    "WORKFLOW_METADATA",
    "read_run_record",
    "write_run_record",
]

STATUS_TOPIC = "/osmo/status"
LINEAGE_TOPIC = "/osmo/lineage"
LOG_TOPIC = "/osmo/log"
LOGS_TOPIC = "/osmo/logs"
"""Where version 1 records kept log lines (JSON); read, never written."""
WORKFLOW_METADATA = "osmo.workflow"
RECORD_VERSION = "2"
READS_VERSIONS = ("1", "2")

_STR = {"type": "string"}
_OPT_STR = {"type": ["string", "null"]}
_OPT_INT = {"type": ["integer", "null"]}
_OPT_NUM = {"type": ["number", "null"]}

STATUS_SCHEMA: dict[str, Any] = {
    "title": "osmo.StatusTransition",
    "description": "A workflow (task null) or task retry changed status.",
    "type": "object",
    "properties": {
        "at": {"type": "number", "description": "unix seconds"},
        "seq": _OPT_INT,
        "workflow_id": _STR,
        "task": _OPT_STR,
        "retry": _OPT_INT,
        "status": _STR,
        "message": _STR,
    },
    "required": ["at", "workflow_id", "task", "retry", "status", "message"],
}

LINEAGE_SCHEMA: dict[str, Any] = {
    "title": "osmo.Lineage",
    "description": "Who made an attempt's outputs, from what, with what, and when.",
    "type": "object",
    "properties": {
        "workflow_id": _STR,
        "task": _STR,
        "retry": {"type": "integer"},
        "attempt_id": _OPT_STR,
        "node": _STR,
        "command": {"type": ["array", "null"], "items": _STR},
        "plugin": {**_OPT_STR, "description": "type@version"},
        "params": {"type": "object"},
        "image": _OPT_STR,
        "image_id": _OPT_STR,
        "inputs": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {"task": _STR, "workflow_id": _STR, "manifest": _STR},
                "required": ["task", "workflow_id", "manifest"],
            },
        },
        "started_at": _OPT_NUM,
        "ended_at": _OPT_NUM,
        "exit_code": _OPT_INT,
        "manifest_digest": _OPT_STR,
        "osmo_version": _STR,
    },
    "required": ["workflow_id", "task", "retry"],
}

def write_run_record(path: Path, *, workflow: Mapping[str, Any],
                     transitions: Sequence[Mapping[str, Any]], lineage: Sequence[Lineage],
                     logs: Iterable[Mapping[str, Any]], ordered: bool = False) -> None:
    """Write a workflow's run record to ``path`` atomically (temp file + rename).

    Args:
        path: the ``.mcap`` file to create or replace; its folder is created if missing.
        workflow: at least ``id``, ``name``, ``status``; ``submitted_at``/``ended_at`` in unix
            seconds (or None); any other JSON-safe keys are kept in the metadata's JSON copy.
        transitions: status events as the store returns them: ``at``, ``status``, optional
            ``workflow_id`` (default: the workflow's), ``task``, ``retry``, ``message``, ``seq``.
        lineage: one :class:`Lineage` per attempt.
        logs: log lines: ``ts``, ``task``, ``retry``, ``stream``, ``text``.
        ordered: ``logs`` come in time order (as ``osmo logs`` streams them): they are then
            written as they come, never all held (a big log costs no memory here); otherwise
            they are sorted first.

    Raises:
        UsageError: an event lacks a field or holds a value JSON cannot encode; nothing is
            written (an earlier file at ``path`` is kept).
        InfrastructureError: the file cannot be written.
    """
    workflow_id = _text(workflow, "id", "workflow")
    events = sorted((_transition(e, workflow_id) for e in transitions), key=lambda m: m["at"])
    lines = _line_entries(_log_line(line) for line in logs)
    fallback = _opt_time(workflow.get("submitted_at"), "workflow submitted_at") or 0.0
    attempts = sorted((_lineage_time(r, fallback), n, r) for n, r in enumerate(lineage))
    with JsonMcapWriter(path) as out:
        log = out.add_protobuf_channel(LOG_TOPIC, LOG_SCHEMA, log_schema())
        status = out.add_json_channel(STATUS_TOPIC, "osmo.StatusTransition", STATUS_SCHEMA)
        lineage_channel = out.add_json_channel(LINEAGE_TOPIC, "osmo.Lineage", LINEAGE_SCHEMA)
        statuses = [_status_entry(e, workflow_id) for e in events]
        in_order = lines if ordered else sorted(lines, key=lambda e: e.time_ns)
        for entry in heapq.merge(statuses, in_order, key=lambda e: e.time_ns):
            out.write_encoded(log, encode_log(entry), entry.time_ns)
        for message in events:
            out.write(status, message, _ns(message["at"], "transition 'at'"))
        for when, _, record in attempts:
            out.write(lineage_channel, record.to_dict(), when)
        out.add_metadata(WORKFLOW_METADATA, _workflow_metadata(workflow))


def read_run_record(path: Path) -> dict[str, Any]:
    """Read a run record back.

    Returns:
        ``{"workflow": dict, "status": [dict], "lineage": [Lineage], "logs": [dict]}``, each
        list in log-time order (ties keep write order).

    Raises:
        NotFoundError: no file at ``path``.
        RecordError: the file is not a readable MCAP run record.
    """
    with McapFile(path) as record:
        meta = record.metadata(WORKFLOW_METADATA)
        if not meta:
            raise RecordError(path, f"no {WORKFLOW_METADATA} metadata: not an osmo run record")
        version = meta[-1][1].get("record_version") or "1"
        if version not in READS_VERSIONS:
            raise RecordError(path, f"run record version {version!r}; this osmo reads versions "
                                    f"{', '.join(READS_VERSIONS)} (upgrade osmo)")
        log_topic = LOG_TOPIC if version == "2" else LOGS_TOPIC
        schemas = {c.topic: c for c in record.channels()}
        messages = record.messages([STATUS_TOPIC, LINEAGE_TOPIC, log_topic])
    by_topic: dict[str, list[McapMessage]] = {STATUS_TOPIC: [], LINEAGE_TOPIC: [], log_topic: []}
    for message in messages:
        by_topic[message.topic].append(message)
    try:
        lineage = [Lineage.from_dict(m.value) for m in by_topic[LINEAGE_TOPIC]]
    except UsageError as exc:
        raise RecordError(path, f"malformed {LINEAGE_TOPIC} message: {exc}") from exc
    if version == "1":
        logs = [m.value for m in by_topic[LOGS_TOPIC]]
    else:
        logs = _logs_from_entries(path, schemas.get(LOG_TOPIC), by_topic[LOG_TOPIC])
    return {
        "workflow": _workflow_from_metadata(meta[-1][1]),
        "status": [m.value for m in by_topic[STATUS_TOPIC]],
        "lineage": lineage,
        "logs": logs,
    }


def _logs_from_entries(path: Path, channel: Any, messages: Sequence[McapMessage]
                       ) -> list[dict[str, Any]]:
    """The task output lines among a version 2 record's ``foxglove.Log`` messages."""
    if channel is None:
        return []
    try:
        decode = log_decoder(channel.schema_name, channel.schema)
        entries = [decode(m.data) for m in messages]
    except UsageError as exc:
        raise RecordError(path, f"{LOG_TOPIC}: {exc}") from exc
    logs = []
    for entry in entries:
        if not entry.file:  # a status transition; /osmo/status has it structured
            continue
        task, retry, stream = _split_source(path, entry.file)
        logs.append({"ts": entry.time_ns / 1e9, "task": task, "retry": retry, "stream": stream,
                     "text": entry.message})
    return logs


def _split_source(path: Path, source: str) -> tuple[str, int, str]:
    """``<task>/<retry>/<stream>`` back into its parts."""
    task, _, rest = source.rpartition("/")
    task, _, retry = task.rpartition("/")
    if not task or not retry.isdigit() or not rest:
        raise RecordError(path, f"{LOG_TOPIC}: a log line's file {source!r} is not "
                                "<task>/<retry>/<stream>")
    return task, int(retry), rest


# ------------------------------------------------------------------------------ helpers


def _ns(seconds: Any, what: str) -> int:
    """Unix seconds → integer ns for an MCAP log time (MCAP times are unsigned)."""
    if isinstance(seconds, bool) or not isinstance(seconds, int | float) \
            or not math.isfinite(seconds) or seconds < 0:
        raise UsageError(f"{what} must be unix seconds >= 0, got {seconds!r}")
    return round(seconds * 1e9)


def _text(event: Mapping[str, Any], key: str, what: str) -> str:
    """A required string field (enum members give their value)."""
    value = _plain(event.get(key))
    if not isinstance(value, str):
        raise UsageError(f"{what} needs a string {key!r}, got {value!r}")
    return value


def _plain(value: Any) -> Any:
    """Enum members (TaskStatus, WorkflowStatus) become their value; others pass through."""
    return value.value if isinstance(value, enum.Enum) else value


def _opt_time(value: Any, what: str) -> float | None:
    """None or unix seconds as a float."""
    if value is None:
        return None
    _ns(value, what)
    return float(value)


def _transition(event: Mapping[str, Any], workflow_id: str) -> dict[str, Any]:
    """Project a store event onto the status schema."""
    message = {
        "at": event.get("at"),
        "seq": event.get("seq"),
        "workflow_id": _plain(event.get("workflow_id")) or workflow_id,
        "task": event.get("task"),
        "retry": event.get("retry"),
        "status": _text(event, "status", "a transition"),
        "message": event.get("message") or "",
    }
    _ns(message["at"], "transition 'at'")
    return message


def _lineage_time(record: Any, fallback: float) -> int:
    """An attempt's log time: its end, else its start, else the workflow's submission."""
    if not isinstance(record, Lineage):
        raise UsageError(f"lineage entries must be Lineage, got {type(record).__name__}")
    when = record.ended_at if record.ended_at is not None else record.started_at
    return _ns(when if when is not None else fallback, "lineage time")


def _status_entry(event: Mapping[str, Any], workflow_id: str) -> LogEntry:
    """A status transition as a readable ``foxglove.Log`` line."""
    status, task = event["status"], event["task"]
    level = "ERROR" if status.startswith("FAILED") else \
        "WARNING" if status == "RESCHEDULED" else "INFO"
    text = f"{status}" if task is not None else f"workflow {status}"
    if event["retry"]:
        text += f" (retry {event['retry']})"
    if event["message"]:
        text += f": {event['message']}"
    return LogEntry(_ns(event["at"], "transition 'at'"), level, text,
                    str(task) if task is not None else workflow_id)


def _line_entries(lines: Iterable[Mapping[str, Any]]) -> Iterator[LogEntry]:
    """Task output lines as ``foxglove.Log`` lines, numbered per task, retry and stream."""
    numbers: dict[str, int] = {}
    for line in lines:
        if not isinstance(line["text"], str) or not isinstance(line["task"], str) \
                or not line["task"] or isinstance(line["retry"], bool) \
                or not isinstance(line["retry"], int) or line["retry"] < 0 \
                or not isinstance(line["stream"], str) or not line["stream"]:
            raise UsageError(f"log line {dict(line)!r}: task, stream and text must be "
                             "strings and retry an integer >= 0")
        source = f"{line['task']}/{line['retry']}/{line['stream']}"
        numbers[source] = numbers.get(source, 0) + 1
        yield LogEntry(_ns(line["ts"], "log 'ts'"),
                       "WARNING" if line["stream"] == "stderr" else "INFO",
                       line["text"], line["task"], source, numbers[source])


def _log_line(line: Mapping[str, Any]) -> dict[str, Any]:
    """Project a log line onto the logs schema."""
    missing = [k for k in ("ts", "task", "retry", "stream", "text") if k not in line]
    if missing:
        raise UsageError(f"log line {dict(line)!r} lacks {', '.join(missing)}")
    return {k: _plain(line[k]) for k in ("ts", "task", "retry", "stream", "text")}


def _workflow_metadata(workflow: Mapping[str, Any]) -> dict[str, str]:
    """The flat ``osmo.workflow`` map: readable strings plus a lossless JSON copy."""
    plain = {k: _plain(v) for k, v in workflow.items()}
    out = {
        "record_version": RECORD_VERSION,
        "id": _text(plain, "id", "workflow"),
        "name": str(plain.get("name") or ""),
        "status": str(plain.get("status") or ""),
    }
    for key in ("submitted_at", "ended_at"):
        when = _opt_time(plain.get(key), f"workflow {key}")
        out[key] = "" if when is None else repr(when)
    out["workflow"] = compact_json(plain, f"workflow {out['id']}")
    return out


def _workflow_from_metadata(meta: Mapping[str, str]) -> dict[str, Any]:
    """Inverse of :func:`_workflow_metadata` (falls back to the flat keys)."""
    if "workflow" in meta:
        try:
            loaded = json.loads(meta["workflow"])
        except ValueError:
            loaded = None
        if isinstance(loaded, dict):
            return loaded
    flat: dict[str, Any] = {k: meta.get(k, "") for k in ("id", "name", "status")}
    for key in ("submitted_at", "ended_at"):
        try:
            flat[key] = float(meta[key]) if meta.get(key) else None
        except ValueError:
            flat[key] = None
    return flat
