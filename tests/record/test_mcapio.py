"""The MCAP adapter: lineage-stamped SDK files, reading any MCAP, and error translation."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

import osmo.record
from osmo.errors import InfrastructureError, NotFoundError, OsmoError, UsageError
from osmo.record import (
    JsonMcapWriter,
    Lineage,
    LineageInput,
    LineageMcapWriter,
    McapFile,
    RecordError,
    read_lineage,
    write_run_record,
)

OSMO = Path(osmo.record.__file__).resolve().parents[1]

LINEAGE = Lineage("wf-9", "rollout", 1, attempt_id="att-5", node="robot-1",
                  plugin="sim.rollout@0.3", params={"episodes": 2, "env": "InvertedPendulum-v5"},
                  inputs=(LineageInput("policy", "wf-8", "sha256:" + "d" * 64),),
                  started_at=1_700_000_000.0, osmo_version="0.1.0")

STATE_SCHEMA = {"type": "object", "properties": {"x": {"type": "number"}}}


def _sdk_file(path: Path, lineage: Lineage | None = LINEAGE) -> Path:
    """Write what a task would: one JSON channel, three messages, one attachment."""
    with LineageMcapWriter(path, lineage) as out:
        channel = out.add_json_channel("/robot/state", "robot.State", STATE_SCHEMA)
        for i in range(3):
            out.write(channel, {"x": i * 0.5, "label": "ü"}, log_time_ns=1000 + i)
        out.attach("config.json", b'{"seed": 1}', "application/json")
    return path


def test_sdk_file_carries_its_lineage_as_metadata(tmp_path: Path) -> None:
    path = _sdk_file(tmp_path / "out" / "rollout.mcap")
    with path.open("rb") as f:
        reader = make_reader(f)
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        messages = [(c.topic, m.log_time, json.loads(m.data)) for _, c, m in reader.iter_messages()]
        attachments = [(a.name, a.media_type, a.data) for a in reader.iter_attachments()]
    assert metadata == {"osmo.lineage": LINEAGE.to_metadata()}
    assert messages == [("/robot/state", 1000 + i, {"x": i * 0.5, "label": "ü"}) for i in range(3)]
    assert attachments == [("config.json", "application/json", b'{"seed": 1}')]
    assert read_lineage(path) == LINEAGE


def test_lineage_from_the_task_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OSMO_WORKFLOW_ID", "wf-1")
    monkeypatch.setenv("OSMO_TASK", "record")
    monkeypatch.setenv("OSMO_RETRY", "0")
    path = _sdk_file(tmp_path / "a.mcap", Lineage.from_env())
    found = read_lineage(path)
    assert found is not None and (found.workflow_id, found.task, found.retry) == ("wf-1", "record", 0)


def test_read_lineage_of_a_file_without_one_is_none(tmp_path: Path) -> None:
    assert read_lineage(_sdk_file(tmp_path / "plain.mcap", None)) is None
    foreign = tmp_path / "foreign.mcap"  # written by mcap itself, no summary, no osmo at all
    with foreign.open("wb") as f:
        writer = Writer(f, compression=CompressionType.NONE, use_summary_offsets=False)
        writer.start()
        schema = writer.register_schema("s", "jsonschema", b"{}")
        writer.add_message(writer.register_channel("/t", "json", schema), 1, b"{}", 1)
        writer.add_metadata("other", {"k": "v"})
        writer.finish()
    assert read_lineage(foreign) is None


def test_mcap_file_reads_channels_messages_and_attachments(tmp_path: Path) -> None:
    with McapFile(_sdk_file(tmp_path / "a.mcap")) as f:
        [channel] = f.channels()
        messages = f.messages()
        attachments = f.attachments()
    assert (channel.topic, channel.schema_name, channel.schema_encoding) == (
        "/robot/state", "robot.State", "jsonschema")
    assert json.loads(channel.schema) == STATE_SCHEMA and channel.message_count == 3
    assert [m.value["x"] for m in messages] == [0.0, 0.5, 1.0]
    assert [m.sequence for m in messages] == [0, 1, 2]
    assert attachments[0].data == b'{"seed": 1}'


def test_an_error_inside_the_block_leaves_no_file(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError, match="boom"):
        with LineageMcapWriter(tmp_path / "x.mcap", LINEAGE) as out:
            out.add_json_channel("/t", "T", {})
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_bad_calls_are_usage_errors_and_the_writer_survives_them(tmp_path: Path) -> None:
    path = tmp_path / "x.mcap"
    with JsonMcapWriter(path) as out:
        channel = out.add_json_channel("/t", "T", {"type": "object"})
        with pytest.raises(UsageError, match="not JSON-serialisable"):
            out.write(channel, {"x": {1, 2}})
        with pytest.raises(UsageError, match="unknown MCAP channel"):
            out.write(channel + 7, {})
        with pytest.raises(UsageError, match="nanoseconds"):
            out.write(channel, {}, log_time_ns=-1)
        with pytest.raises(UsageError, match="must be bytes"):
            out.attach("a", "text", "text/plain")  # type: ignore[arg-type]
        with pytest.raises(UsageError, match="strings to strings"):
            out.add_metadata("m", {"k": 1})  # type: ignore[dict-item]
        out.write(channel, {"ok": True}, log_time_ns=5)
    with McapFile(path) as f:
        assert [m.value for m in f.messages()] == [{"ok": True}]
    with pytest.raises(UsageError, match="already closed"):
        out.write(channel, {})


def test_lineage_must_be_a_lineage(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="must be a Lineage"):
        LineageMcapWriter(tmp_path / "x.mcap", {"task": "t"})  # type: ignore[arg-type]
    assert list(tmp_path.iterdir()) == []


def _truncations(good: bytes) -> list[bytes]:
    return [b"", good[:8], good[: len(good) // 2], good[:-1], good[:-30]]


@pytest.mark.parametrize("cut", range(5))
def test_truncated_files_raise_record_error(tmp_path: Path, cut: int) -> None:
    good = _sdk_file(tmp_path / "good.mcap").read_bytes()
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(_truncations(good)[cut])
    with pytest.raises(RecordError, match=re.escape(str(bad))) as info:
        read_lineage(bad)
    assert isinstance(info.value, OsmoError) and info.value.exit_code == 2
    assert info.value.path == bad


@pytest.mark.parametrize("content", [b"not an mcap file at all\n" * 10, bytes(range(256)) * 4])
def test_foreign_files_raise_record_error(tmp_path: Path, content: bytes) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(content)
    with pytest.raises(RecordError, match="not a readable MCAP"):
        read_lineage(bad)


def test_corrupt_chunk_raises_record_error_when_read(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    logs = [{"ts": 1.0 + i, "task": "t", "retry": 0, "stream": "stdout", "text": f"line {i}"}
            for i in range(50)]
    write_run_record(path, workflow={"id": "w", "name": "w", "status": "COMPLETED"},
                     transitions=[], lineage=[], logs=logs)
    data = bytearray(path.read_bytes())
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    chunk = summary.chunk_indexes[0]
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[middle:middle + 16] = b"\xff" * 16
    path.write_bytes(bytes(data))
    with McapFile(path) as f, pytest.raises(RecordError):
        f.messages()


def test_missing_file_is_not_found(tmp_path: Path) -> None:
    with pytest.raises(NotFoundError, match="no such MCAP file"):
        read_lineage(tmp_path / "nope.mcap")


def test_malformed_lineage_metadata_is_a_record_error(tmp_path: Path) -> None:
    path = tmp_path / "x.mcap"
    with JsonMcapWriter(path) as out:
        out.add_metadata("osmo.lineage", {"task": "t", "retry": "oops"})
    with pytest.raises(RecordError, match="malformed osmo.lineage"):
        read_lineage(path)


def test_only_mcapio_imports_mcap() -> None:
    importers = sorted(
        str(p.relative_to(OSMO)) for p in OSMO.rglob("*.py")
        if re.search(r"^\s*(import mcap|from mcap)\b", p.read_text(encoding="utf-8"), re.M)
    )
    assert importers == ["record/mcapio.py"]


def test_public_names_are_exported_and_documented() -> None:
    for name in osmo.record.__all__:
        value = getattr(osmo.record, name)
        if callable(value):
            assert value.__doc__, name
    assert issubclass(RecordError, UsageError)


def test_unserialisable_lineage_fails_the_close_and_leaves_no_file(tmp_path: Path) -> None:
    bad = Lineage("wf", "t", params={"obj": object()})
    with pytest.raises(UsageError, match="not JSON-serialisable"):
        with LineageMcapWriter(tmp_path / "x.mcap", bad) as out:
            out.add_json_channel("/t", "T", {})
    assert list(tmp_path.iterdir()) == []


def test_an_unexpected_writer_failure_aborts_the_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = JsonMcapWriter(tmp_path / "x.mcap")
    channel = out.add_json_channel("/t", "T", {})

    def explode(*args: object, **kwargs: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(out._writer, "add_message", explode)
    with pytest.raises(InfrastructureError, match="No space left"):
        out.write(channel, {"x": 1})
    assert list(tmp_path.iterdir()) == []
    out.abort()  # idempotent
