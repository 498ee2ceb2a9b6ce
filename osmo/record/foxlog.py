"""The one module of osmo's core that imports protobuf: ``foxglove.Log`` messages for MCAP.

Foxglove's Log panel shows messages of the standard ``foxglove.Log`` schema (timestamp, level,
message, name, file, line). The schema is never spelled here: the message class and its
``FileDescriptorSet`` come from Foxglove's own precompiled schemas
(``foxglove-schemas-protobuf``), and reading decodes with the schema the file declares, so a
record written by another version of those schemas still reads.

Errors from protobuf are translated here: a message or schema that does not parse raises
:class:`osmo.errors.UsageError` (the caller names the file).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from foxglove_schemas_protobuf.Log_pb2 import Log
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import DecodeError

from osmo.errors import UsageError

__all__ = ["LEVELS", "LOG_SCHEMA", "LogEntry", "encode_log", "log_decoder", "log_schema",
           "message_class"]

LOG_SCHEMA = Log.DESCRIPTOR.full_name
"""The schema name a ``foxglove.Log`` channel declares."""

LEVELS = tuple(name for name, _ in Log.Level.items())
"""Level names, by number: UNKNOWN, DEBUG, INFO, WARNING, ERROR, FATAL."""


@dataclass(frozen=True)
class LogEntry:
    """One ``foxglove.Log`` message.

    Attributes:
        time_ns: its timestamp, ns since the unix epoch (also its MCAP log time).
        level: one of :data:`LEVELS`.
        message: the text.
        name: who logged it (osmo: the task, or the workflow id for workflow events).
        file: where it came from (osmo: ``<task>/<retry>/<stream>`` for a task's output line,
            empty for a status event).
        line: the line number in ``file`` (1-based; 0 when there is no file).
    """

    time_ns: int
    level: str
    message: str
    name: str
    file: str = ""
    line: int = 0


def log_schema() -> bytes:
    """The serialized ``FileDescriptorSet`` of ``foxglove.Log`` and the files it imports."""
    files: list[Any] = []
    seen: set[str] = set()

    def add(file: Any) -> None:
        if file.name in seen:
            return
        seen.add(file.name)
        for dependency in file.dependencies:  # dependencies first, as a pool needs them
            add(dependency)
        proto = descriptor_pb2.FileDescriptorProto()
        file.CopyToProto(proto)
        files.append(proto)

    add(Log.DESCRIPTOR.file)
    return bytes(descriptor_pb2.FileDescriptorSet(file=files).SerializeToString())


def encode_log(entry: LogEntry) -> bytes:
    """Serialize one entry as a ``foxglove.Log`` message.

    Raises:
        UsageError: an unknown level or a line number outside 0..2**32-1.
    """
    if entry.level not in LEVELS:
        raise UsageError(f"log level must be one of {', '.join(LEVELS)}, got {entry.level!r}")
    if not 0 <= entry.line < 2**32:
        raise UsageError(f"log line number out of range: {entry.line!r}")
    message = Log(level=Log.Level.Value(entry.level), message=entry.message, name=entry.name,
                  file=entry.file, line=entry.line)
    message.timestamp.seconds, message.timestamp.nanos = divmod(entry.time_ns, 1_000_000_000)
    return bytes(message.SerializeToString())


def message_class(schema_name: str, descriptor_set: bytes) -> Any:
    """The protobuf message class ``schema_name`` as a serialized ``FileDescriptorSet`` declares it.

    What an MCAP ``protobuf`` channel's schema holds; the class is built from it, not taken
    from the classes installed here.

    Raises:
        UsageError: the descriptor set does not parse or lacks ``schema_name``.
    """
    try:
        fds = descriptor_pb2.FileDescriptorSet.FromString(descriptor_set)
        pool = descriptor_pool.DescriptorPool()
        for proto in fds.file:
            pool.Add(proto)
        return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))
    except (DecodeError, KeyError, TypeError, ValueError) as exc:
        raise UsageError(f"schema {schema_name!r} is not a protobuf descriptor set declaring "
                         f"it: {exc}") from exc


def log_decoder(schema_name: str, descriptor_set: bytes) -> Callable[[bytes], LogEntry]:
    """A decoder for messages of a channel declaring ``schema_name`` with ``descriptor_set``.

    The message type is built from the declared schema (:func:`message_class`) and must be
    ``foxglove.Log``.

    Raises:
        UsageError: the schema is not ``foxglove.Log`` or does not parse; the decoder raises it
            for a message that does not parse.
    """
    if schema_name != LOG_SCHEMA:
        raise UsageError(f"expected a {LOG_SCHEMA} channel, found schema {schema_name!r}")
    cls = message_class(schema_name, descriptor_set)

    def decode(data: bytes) -> LogEntry:
        try:
            message = cls.FromString(data)
        except DecodeError as exc:
            raise UsageError(f"unreadable {schema_name} message: {exc}") from exc
        level = LEVELS[message.level] if 0 <= message.level < len(LEVELS) else "UNKNOWN"
        stamp = message.timestamp.seconds * 1_000_000_000 + message.timestamp.nanos
        return LogEntry(stamp, level, message.message, message.name, message.file, message.line)

    return decode
