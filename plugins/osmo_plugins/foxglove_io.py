"""The one module of the plugins that imports the Foxglove SDK and protobuf.

Owns :class:`FoxgloveMcapWriter` (an MCAP file written by the Foxglove SDK's Rust writer:
protobuf channels of our own schemas, ``foxglove.RawImage`` frames, metadata records; the file
appears under its name only on close, like every osmo output), :class:`ProtoSchema` (a proto3
message type declared in code, with the ``FileDescriptorSet`` that MCAP stores as its schema),
and :func:`protobuf_decoder` (a decoder built from the schema a file declares, so any channel
reads back without knowing its type in advance).

The SDK writes the standard schemas itself; nothing here spells a Foxglove schema by hand.
Foxglove's MCAP writer costs ~1 µs per message here against ~3.5 µs for the pure-Python
``mcap`` writer, which is what keeps per-step recording within budget (bench/bench_datagen.py).
Errors from the SDK and protobuf are translated here: a write that fails raises
:class:`osmo.errors.InfrastructureError`, a schema that does not parse ``RecordError``.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import IO, Any

from osmo.errors import InfrastructureError, UsageError
from osmo.record import RecordError
from osmo_plugins._base import Committing

__all__ = ["FoxgloveMcapWriter", "ProtoSchema", "protobuf_decoder", "require_foxglove"]

_SCALARS = {"uint32": 13, "fixed32": 7, "int64": 3, "float": 2, "double": 1, "bool": 8,
            "string": 9}
"""proto3 field types by name (``FieldDescriptorProto.Type`` numbers)."""


def require_foxglove() -> Any:
    """Import the Foxglove SDK or say which extra installs it."""
    try:
        import foxglove
    except ImportError as exc:
        raise UsageError(f'writing episodes needs the Foxglove SDK: pip install "osmo[sim]" '
                         f"({exc})") from exc
    return foxglove


class ProtoSchema:
    """A proto3 message type declared as ``(name, type, repeated)`` fields, numbered in order.

    Args:
        full_name: ``package.Message`` (e.g. ``osmo.EpisodeStep``).
        fields: field name, scalar type (``fixed32``, ``float``, ``double``, ``bool``, ...)
            and whether it repeats (repeated numbers are packed, as proto3 does).

    Attributes:
        message: the generated message class (``message(**fields).SerializeToString()``).
        data: the serialized ``FileDescriptorSet``, what an MCAP ``protobuf`` schema holds.
    """

    def __init__(self, full_name: str, fields: Sequence[tuple[str, str, bool]]) -> None:
        from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

        package, _, name = full_name.rpartition(".")
        proto = descriptor_pb2.FileDescriptorProto(
            name=f"{full_name.replace('.', '/')}.proto", package=package, syntax="proto3")
        message = proto.message_type.add(name=name)
        for number, (field, kind, repeated) in enumerate(fields, start=1):
            message.field.add(name=field, number=number, type=_SCALARS[kind],
                              label=3 if repeated else 1)
        pool = descriptor_pool.DescriptorPool()
        pool.Add(proto)
        self.name = full_name
        self.message: Any = message_factory.GetMessageClass(pool.FindMessageTypeByName(full_name))
        self.data = descriptor_pb2.FileDescriptorSet(file=[proto]).SerializeToString()


def protobuf_decoder(schema_name: str, schema_data: bytes, path: Path | str
                     ) -> Callable[[bytes], Any]:
    """A function decoding one message of a ``protobuf`` channel.

    It is built from the schema the file declares (a serialized ``FileDescriptorSet``).

    Raises:
        RecordError: the schema does not parse or lacks the named message type.
    """
    from google.protobuf.message import DecodeError

    from osmo.record.foxlog import message_class

    try:
        cls = message_class(schema_name, schema_data)
    except UsageError as exc:
        raise RecordError(path, str(exc)) from exc

    def decode(data: bytes) -> Any:
        try:
            return cls.FromString(data)
        except DecodeError as exc:
            raise RecordError(path, f"a {schema_name} message does not decode: {exc}") from exc

    return decode


class FoxgloveMcapWriter(Committing):
    """One MCAP file written by the Foxglove SDK; it appears under ``path`` only on close.

    Each writer has its own SDK ``Context``, so two files open in one process never see each
    other's channels. As a context manager, an exception discards the file.

    Raises:
        InfrastructureError: the temp file cannot be created.
    """

    def __init__(self, path: Path | str, *, profile: str = "") -> None:
        fox = require_foxglove()
        from foxglove.mcap import MCAPWriteOptions

        self.path = Path(path)
        self._tmp = self.path.with_name(f".{self.path.name}.{uuid.uuid4().hex[:12]}.partial")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file: IO[bytes] = open(self._tmp, "xb")
        except OSError as exc:
            raise InfrastructureError(f"cannot create {self.path}: {exc}") from exc
        self._fox = fox
        self._context = fox.Context()
        # One compression thread: tasks share the machine's cores with other tasks.
        options = MCAPWriteOptions(profile=profile or None, compression_threads=0)
        self._writer = fox.open_mcap(self._file, context=self._context, writer_options=options)
        self._channels: list[Any] = []
        self._closed = False

    def protobuf_channel(self, topic: str, schema: ProtoSchema) -> Callable[[bytes, int], None]:
        """Register ``topic`` with ``schema``; returns ``log(data, log_time_ns)``."""
        channel = self._fox.Channel(
            topic, message_encoding="protobuf", context=self._context,
            schema=self._fox.Schema(name=schema.name, encoding="protobuf", data=schema.data))
        self._channels.append(channel)
        return channel.base.log

    def raw_image_channel(self, topic: str, frame_id: str = "camera"
                          ) -> Callable[[Any, int], None]:
        """Register a ``foxglove.RawImage`` channel; returns ``log(rgb_uint8_hwc, log_time_ns)``."""
        from foxglove.channels import RawImageChannel
        from foxglove.messages import RawImage, Timestamp

        channel = RawImageChannel(topic, context=self._context)
        self._channels.append(channel)

        def log(frame: Any, log_time: int) -> None:
            height, width = int(frame.shape[0]), int(frame.shape[1])
            stamp = Timestamp(sec=log_time // 1_000_000_000, nsec=log_time % 1_000_000_000)
            channel.log(RawImage(timestamp=stamp, frame_id=frame_id, width=width,
                                 height=height, encoding="rgb8", step=width * 3,
                                 data=frame.tobytes()), log_time=log_time)

        return log

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Write a metadata record (a name and a flat map of strings)."""
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
            raise UsageError(f"metadata {name!r} must map strings to strings")
        self._writer.write_metadata(name, dict(data))

    def close(self) -> None:
        """Finish the file, sync it and rename it into place."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.close()
            for channel in self._channels:
                channel.close()
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            os.replace(self._tmp, self.path)
        except Exception as exc:
            self._discard()
            raise InfrastructureError(f"cannot write {self.path}: {exc}") from exc

    def abort(self) -> None:
        """Discard the file; ``path`` is left untouched."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.close()
        finally:
            self._discard()

    def _discard(self) -> None:
        try:
            self._file.close()
        finally:
            self._tmp.unlink(missing_ok=True)
