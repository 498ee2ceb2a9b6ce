"""The one module of osmo that imports ``mcap``: MCAP writing and reading.

Owns :class:`JsonMcapWriter` (one MCAP file of JSON-schema channels, protobuf channels whose
messages the caller encodes, metadata and attachments, written atomically: a hidden temp file
renamed into place on close), :class:`LineageMcapWriter`
(the same, stamping an ``osmo.lineage`` metadata record; what task code uses), and
:class:`McapFile` / :func:`read_lineage` (reading any MCAP file back).

Errors from ``mcap`` and its codecs are translated here: an unreadable file raises
:class:`RecordError`, a bad argument ``UsageError``, a failed write ``InfrastructureError``.
It must not know about workflows or the server (the run record's layout is in ``runrecord``).
"""

from __future__ import annotations

import json
import os
import struct
import time
import uuid
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Self

import mcap.writer as _mcap_writer
from mcap.exceptions import EndOfFile, UnsupportedCompressionError
from mcap.reader import McapReader, make_reader
from mcap.writer import CompressionType, Writer

from osmo.errors import InfrastructureError, NotFoundError, OsmoError, UsageError
from osmo.record.lineage import LINEAGE_METADATA, Lineage, compact_json

__all__ = [
    "Attachment", "ChannelInfo", "JsonMcapWriter", "LineageMcapWriter", "McapFile",
    "McapMessage", "RecordError", "json_bytes", "read_lineage",
]

_U64 = 2**64


class RecordError(UsageError):
    """A file is not a readable MCAP: corrupt, truncated, not MCAP, or needs a missing codec.

    Attributes:
        path: the file that could not be read.
    """

    def __init__(self, path: Path | str, reason: str) -> None:
        self.path = Path(path)
        super().__init__(f"{path}: not a readable MCAP file ({reason})")


def json_bytes(value: Any, what: str = "value") -> bytes:
    """Encode ``value`` as compact UTF-8 JSON (no NaN/Infinity, which viewers reject).

    Raises:
        UsageError: the value is not JSON-serialisable; ``what`` names it in the message.
    """
    return compact_json(value, what).encode("utf-8")


def _best_compression() -> CompressionType:
    """zstd, else lz4, else none: whichever codec ``mcap.writer`` managed to import."""
    if getattr(_mcap_writer, "zstandard", None) is not None:
        return CompressionType.ZSTD
    if getattr(_mcap_writer, "lz4", None) is not None:
        return CompressionType.LZ4
    return CompressionType.NONE


def _check_time(value: int | None, what: str) -> int:
    """A log time in ns (now when None); MCAP stores unsigned 64-bit integers."""
    if value is None:
        return time.time_ns()
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < _U64:
        raise UsageError(f"{what} must be an integer of nanoseconds >= 0, got {value!r}")
    return value


class JsonMcapWriter:
    """Writes one MCAP file of JSON channels; the file appears under ``path`` only on close.

    As a context manager: leaving the block normally finishes and renames the file; leaving
    it with an exception deletes the temp file and keeps any earlier file at ``path``.

    Args:
        path: the final file name; its folder is created if missing.
        compress: compress chunks with zstd or lz4 when installed (else write uncompressed).
        profile: the MCAP header profile (empty: no well-known profile).

    Raises:
        InfrastructureError: the temp file cannot be created.
    """

    def __init__(self, path: Path | str, *, compress: bool = True, profile: str = "") -> None:
        from osmo.version import __version__

        self.path = Path(path)
        self._tmp = self.path.with_name(f".{self.path.name}.{uuid.uuid4().hex[:12]}.partial")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file: IO[bytes] = open(self._tmp, "xb")
        except OSError as exc:
            raise InfrastructureError(f"cannot create {self.path}: {exc}") from exc
        compression = _best_compression() if compress else CompressionType.NONE
        self._writer = Writer(self._file, compression=compression)
        self._topics: dict[int, str] = {}
        self._sequence: dict[int, int] = {}
        self._schemas: dict[tuple[str, bytes], int] = {}
        self._closed = False
        with self._writing():
            self._writer.start(profile=profile, library=f"osmo {__version__}")

    def __enter__(self) -> Self:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if kind is None:
            self.close()
        else:
            self.abort()

    @contextmanager
    def _writing(self, *, finishing: bool = False) -> Iterator[None]:
        """Translate write failures and abort the file: a half-written MCAP is junk.

        An osmo error (raised before anything was written) aborts only while ``finishing``.
        """
        if self._closed:
            raise UsageError(f"{self.path}: the MCAP writer is already closed")
        try:
            yield
        except OsmoError:
            if finishing:
                self.abort()
            raise
        except (OSError, struct.error, UnsupportedCompressionError) as exc:
            self.abort()
            raise InfrastructureError(f"cannot write {self.path}: {exc}") from exc
        except BaseException:
            self.abort()
            raise

    def add_json_channel(self, topic: str, schema_name: str, schema: Mapping[str, Any]) -> int:
        """Register a channel (e.g. ``/robot/state``) of JSON messages.

        They are described by a JSON Schema named ``schema_name`` (stored with encoding
        ``jsonschema``).

        Returns:
            the channel id to pass to :meth:`write`.
        """
        data = json_bytes(schema, f"JSON schema {schema_name!r}")
        return self._add_channel(topic, schema_name, "jsonschema", data, "json")

    def add_protobuf_channel(self, topic: str, schema_name: str, descriptor_set: bytes) -> int:
        """Register a channel of protobuf messages of type ``schema_name`` (e.g. ``foxglove.Log``).

        ``descriptor_set`` is the serialized ``FileDescriptorSet`` declaring that type, which is
        what MCAP readers (Foxglove among them) decode a ``protobuf`` channel with.

        Returns:
            the channel id to pass to :meth:`write_encoded`.
        """
        if not isinstance(descriptor_set, bytes) or not descriptor_set:
            raise UsageError(f"protobuf schema {schema_name!r} needs a FileDescriptorSet")
        return self._add_channel(topic, schema_name, "protobuf", descriptor_set, "protobuf")

    def _add_channel(self, topic: str, schema_name: str, schema_encoding: str, data: bytes,
                     message_encoding: str) -> int:
        if not topic or not schema_name:
            raise UsageError("an MCAP channel needs a non-empty topic and schema name")
        with self._writing():
            schema_id = self._schemas.get((schema_name, data))
            if schema_id is None:
                schema_id = self._writer.register_schema(schema_name, schema_encoding, data)
                self._schemas[(schema_name, data)] = schema_id
            channel_id: int = self._writer.register_channel(topic, message_encoding, schema_id)
        self._topics[channel_id] = topic
        self._sequence[channel_id] = 0
        return channel_id

    def write(self, channel_id: int, obj: Any, log_time_ns: int | None = None) -> None:
        """Write one JSON-serialisable ``obj`` to a channel from :meth:`add_json_channel`.

        It is stamped ``log_time_ns`` (ns since the unix epoch; default: now).

        Raises:
            UsageError: unknown channel, bad time, or ``obj`` is not JSON-serialisable.
        """
        if channel_id not in self._topics:
            raise UsageError(f"unknown MCAP channel id {channel_id!r}: use add_json_channel()")
        self.write_encoded(channel_id, json_bytes(obj, f"message on {self._topics[channel_id]}"),
                           log_time_ns)

    def write_encoded(self, channel_id: int, data: bytes, log_time_ns: int | None = None) -> None:
        """Write one message already encoded in its channel's encoding (e.g. protobuf bytes).

        Raises:
            UsageError: unknown channel or bad time.
        """
        if channel_id not in self._topics:
            raise UsageError(f"unknown MCAP channel id {channel_id!r}: add the channel first")
        stamp = _check_time(log_time_ns, "log_time_ns")
        with self._writing():
            self._writer.add_message(channel_id, log_time=stamp, data=data, publish_time=stamp,
                                     sequence=self._sequence[channel_id] % 2**32)
        self._sequence[channel_id] += 1

    def attach(self, name: str, data: bytes, media_type: str = "application/octet-stream",
               log_time_ns: int | None = None) -> None:
        """Attach a named blob (a config, a small checkpoint) to the file."""
        if not isinstance(data, bytes | bytearray | memoryview):
            raise UsageError(f"attachment {name!r} must be bytes, got {type(data).__name__}")
        stamp = _check_time(log_time_ns, "log_time_ns")
        with self._writing():
            self._writer.add_attachment(create_time=stamp, log_time=stamp, name=name,
                                        media_type=media_type, data=bytes(data))

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Add a metadata record: a name and a flat map of strings."""
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
            raise UsageError(f"metadata {name!r} must map strings to strings")
        with self._writing():
            self._writer.add_metadata(name, dict(data))

    def close(self) -> None:
        """Finish the file (summary and indexes), sync it, and rename it into place."""
        if self._closed:
            return
        with self._writing(finishing=True):
            self._before_finish()
            self._writer.finish()  # type: ignore[no-untyped-call]
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            os.replace(self._tmp, self.path)
        self._closed = True

    def _before_finish(self) -> None:
        """Hook for subclasses: last records to write before the summary."""

    def abort(self) -> None:
        """Discard the file: close and delete the temp file; ``path`` is left untouched."""
        self._closed = True
        try:
            self._file.close()
        finally:
            self._tmp.unlink(missing_ok=True)


class LineageMcapWriter(JsonMcapWriter):
    """An MCAP writer for task code that stamps the file with where it came from.

    On close it writes an ``osmo.lineage`` metadata record (when ``lineage`` is given), so
    the file says which workflow, task and attempt made it even after it leaves osmo::

        with LineageMcapWriter(out / "rollout.mcap", Lineage.from_env()) as mc:
            ch = mc.add_json_channel("/state", "State", {"type": "object"})
            mc.write(ch, {"x": 1.0})

    ``lineage`` may be None (a plain MCAP); ``path`` and ``compress`` are as for
    :class:`JsonMcapWriter`.
    """

    def __init__(self, path: Path | str, lineage: Lineage | None, *,
                 compress: bool = True) -> None:
        if lineage is not None and not isinstance(lineage, Lineage):
            raise UsageError(f"lineage must be a Lineage or None, got {type(lineage).__name__}")
        self.lineage = lineage
        super().__init__(path, compress=compress)

    def _before_finish(self) -> None:
        if self.lineage is not None:
            self._writer.add_metadata(LINEAGE_METADATA, self.lineage.to_metadata())


# ---------------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class ChannelInfo:
    """A channel as the file describes it.

    Schema fields are empty when it has no schema; ``message_count`` comes from the file's
    statistics (None when it has none).
    """

    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    schema: bytes
    message_count: int | None


@dataclass(frozen=True)
class McapMessage:
    """One message: ``value`` is the decoded JSON for ``json`` channels, else None."""

    topic: str
    log_time_ns: int
    sequence: int
    data: bytes
    value: Any


@dataclass(frozen=True)
class Attachment:
    """One attachment record."""

    name: str
    media_type: str
    log_time_ns: int
    data: bytes


class McapFile:
    """Reads one MCAP file; every decoding failure raises :class:`RecordError`.

    Args:
        path: the file to open.

    Raises:
        NotFoundError: no file at ``path``.
        RecordError: the file does not start like an MCAP file.
    """

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        with self._reading():
            self._file: IO[bytes] = open(self.path, "rb")
        try:
            with self._reading():
                # CRCs checked: a corrupt chunk of protobuf (no JSON to fail parsing) must not
                # read as data.
                self._reader: McapReader = make_reader(self._file, validate_crcs=True)
                self._summary = self._reader.get_summary()
        except BaseException:
            self._file.close()
            raise

    def __enter__(self) -> McapFile:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the underlying file."""
        self._file.close()

    @contextmanager
    def _reading(self) -> Iterator[None]:
        """Translate anything the reader raises into an osmo error naming the file."""
        try:
            yield
        except OsmoError:
            raise
        except (FileNotFoundError, IsADirectoryError) as exc:
            raise NotFoundError(f"{self.path}: no such MCAP file") from exc
        except UnsupportedCompressionError as exc:
            raise RecordError(self.path, f"{exc}; pip install zstandard lz4") from exc
        except EndOfFile as exc:
            raise RecordError(self.path, "truncated: it ends in the middle of a record") from exc
        except Exception as exc:  # noqa: BLE001 - a corrupt file surfaces as any of a dozen
            # types (McapError, struct.error, ValueError, KeyError, OSError from a seek before
            # the start, zstd/lz4 errors); all mean the same thing to the caller.
            raise RecordError(self.path, f"{type(exc).__name__}: {exc}") from exc

    def channels(self) -> list[ChannelInfo]:
        """Every channel, by id (read from the summary; a file without one is scanned)."""
        with self._reading():
            if self._summary is None:
                seen = {c.id: (s, c) for s, c, _ in self._reader.iter_messages()}
                pairs, counts = list(seen.values()), {}
            else:
                pairs = [(self._summary.schemas.get(c.schema_id), c)
                         for c in self._summary.channels.values()]
                stats = self._summary.statistics
                counts = dict(stats.channel_message_counts) if stats else {}
        return [ChannelInfo(c.topic, c.message_encoding, s.name if s else "",
                            s.encoding if s else "", s.data if s else b"", counts.get(c.id))
                for s, c in sorted(pairs, key=lambda p: p[1].id)]

    def messages(self, topics: Iterable[str] | None = None) -> list[McapMessage]:
        """Messages (optionally of some topics) in log-time order, JSON decoded where JSON."""
        out: list[McapMessage] = []
        with self._reading():
            wanted = list(topics) if topics is not None else None
            for _, channel, msg in self._reader.iter_messages(topics=wanted):
                value = None
                if channel.message_encoding == "json":
                    value = json.loads(msg.data)
                out.append(McapMessage(channel.topic, msg.log_time, msg.sequence, msg.data, value))
        return out

    def metadata(self, name: str | None = None) -> list[tuple[str, dict[str, str]]]:
        """Metadata records as ``(name, map)``, in file order; only ``name``'s when given."""
        with self._reading():
            records = [(m.name, dict(m.metadata)) for m in self._reader.iter_metadata()]
        return [r for r in records if name is None or r[0] == name]

    def attachments(self) -> list[Attachment]:
        """Every attachment, in file order."""
        with self._reading():
            return [Attachment(a.name, a.media_type, a.log_time, bytes(a.data))
                    for a in self._reader.iter_attachments()]


def read_lineage(path: Path | str) -> Lineage | None:
    """Return the lineage stamped in any MCAP file, or None when it carries none.

    Works on a file far from osmo's store: the ``osmo.lineage`` metadata record is all it needs.
    When a file holds several (it should not), the last one wins.

    Raises:
        NotFoundError: no file at ``path``.
        RecordError: the file is not a readable MCAP, or its lineage record is malformed.
    """
    with McapFile(path) as mcap_file:
        records = mcap_file.metadata(LINEAGE_METADATA)
    if not records:
        return None
    try:
        return Lineage.from_metadata(records[-1][1])
    except UsageError as exc:
        raise RecordError(path, f"malformed {LINEAGE_METADATA} record: {exc}") from exc
