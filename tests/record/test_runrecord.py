"""Run records: real MCAP files written by osmo and read back with mcap's own reader."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

import osmo.record.mcapio as mcapio
from osmo.errors import UsageError
from osmo.record import (
    LINEAGE_TOPIC,
    LOG_TOPIC,
    LOGS_TOPIC,
    STATUS_TOPIC,
    JsonMcapWriter,
    LineageMcapWriter,
    RecordError,
    read_run_record,
    write_run_record,
)
from osmo.record.lineage import Lineage, LineageInput
from osmo.status import TaskStatus, WorkflowStatus

T0 = 1_700_000_000.0

WORKFLOW = {"id": "wf-42", "name": "pendulum", "status": "COMPLETED",
            "submitted_at": T0, "ended_at": T0 + 9.5}

TRANSITIONS = [
    {"seq": 1, "at": T0, "workflow_id": "wf-42", "task": None, "retry": None,
     "status": "PENDING", "message": ""},
    {"seq": 2, "at": T0 + 1, "workflow_id": "wf-42", "task": "sim", "retry": 0,
     "status": "RUNNING", "message": "on node-a"},
    {"seq": 3, "at": T0 + 4, "workflow_id": "wf-42", "task": "sim", "retry": 0,
     "status": "COMPLETED", "message": ""},
    {"seq": 4, "at": T0 + 9.5, "workflow_id": "wf-42", "task": None, "retry": None,
     "status": "COMPLETED", "message": "all tasks done"},
]

LINEAGE = [
    Lineage("wf-42", "sim", 0, attempt_id="att-1", node="node-a",
            command=("python", "-c", "print('hi')"), started_at=T0 + 1, ended_at=T0 + 4,
            exit_code=0, manifest_digest="sha256:" + "c" * 64, osmo_version="0.1.0"),
    Lineage("wf-42", "train", 0, attempt_id="att-2", node="node-b", plugin="learn.act@0.2",
            params={"steps": 10}, inputs=(LineageInput("sim", "wf-42", "sha256:" + "c" * 64),),
            started_at=T0 + 4.5, ended_at=T0 + 9, exit_code=0, osmo_version="0.1.0"),
]

LOGS = [
    {"ts": T0 + 1.5, "task": "sim", "retry": 0, "stream": "stdout", "text": "héllo wörld ✓ 日本語 🤖"},
    {"ts": T0 + 2.0, "task": "sim", "retry": 0, "stream": "stderr", "text": "warning: ∂x/∂t"},
    {"ts": T0 + 5.0, "task": "train", "retry": 0, "stream": "stdout", "text": "step 1"},
]


@pytest.fixture
def record(tmp_path: Path) -> Path:
    """A run record written with every kind of event."""
    path = tmp_path / "records" / "wf-42.mcap"
    write_run_record(path, workflow=WORKFLOW, transitions=TRANSITIONS, lineage=LINEAGE, logs=LOGS)
    return path


def _decoded(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """Every message by topic as (log time, value), decoded with the schema the file declares.

    JSON channels with json; protobuf channels with a message class built from the channel's
    own FileDescriptorSet (nothing of osmo's).
    """
    out: dict[str, list[tuple[int, Any]]] = {}
    classes: dict[int, Any] = {}
    with path.open("rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            assert schema is not None
            if channel.message_encoding == "json":
                assert schema.encoding == "jsonschema"
                value = json.loads(message.data)
            else:
                assert (channel.message_encoding, schema.encoding) == ("protobuf", "protobuf")
                if schema.id not in classes:
                    pool = descriptor_pool.DescriptorPool()
                    for proto in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
                        pool.Add(proto)
                    classes[schema.id] = message_factory.GetMessageClass(
                        pool.FindMessageTypeByName(schema.name))
                value = classes[schema.id].FromString(message.data)
            out.setdefault(channel.topic, []).append((message.log_time, value))
    return out


def test_channels_declare_their_schemas_and_counts(record: Path) -> None:
    with record.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    channels = {c.topic: c for c in summary.channels.values()}
    assert sorted(channels) == sorted([STATUS_TOPIC, LINEAGE_TOPIC, LOG_TOPIC])
    for topic in (STATUS_TOPIC, LINEAGE_TOPIC):
        schema = summary.schemas[channels[topic].schema_id]
        assert channels[topic].message_encoding == "json"
        assert schema.encoding == "jsonschema"
        assert json.loads(schema.data)["type"] == "object"
    log_schema = summary.schemas[channels[LOG_TOPIC].schema_id]
    assert (log_schema.name, log_schema.encoding) == ("foxglove.Log", "protobuf")
    assert channels[LOG_TOPIC].message_encoding == "protobuf"
    assert summary.statistics is not None
    counts = summary.statistics.channel_message_counts
    assert counts[channels[STATUS_TOPIC].id] == len(TRANSITIONS)
    assert counts[channels[LINEAGE_TOPIC].id] == len(LINEAGE)
    assert counts[channels[LOG_TOPIC].id] == len(TRANSITIONS) + len(LOGS)


def test_every_message_decodes_and_times_are_monotonic_per_channel(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    shuffled = [TRANSITIONS[2], TRANSITIONS[0], TRANSITIONS[3], TRANSITIONS[1]]
    write_run_record(path, workflow=WORKFLOW, transitions=shuffled, lineage=LINEAGE[::-1],
                     logs=[LOGS[2], LOGS[0], LOGS[1]])
    topics = _decoded(path)
    assert set(topics) == {STATUS_TOPIC, LINEAGE_TOPIC, LOG_TOPIC}
    for rows in topics.values():  # in file order, as written
        times = [t for t, _ in rows]
        assert times == sorted(times)
    for stamp, log in topics[LOG_TOPIC]:
        assert log.timestamp.seconds * 10**9 + log.timestamp.nanos == stamp


def test_the_log_channel_is_foxglove_log_for_lines_and_transitions(record: Path) -> None:
    logs = [(t, m) for t, m in _decoded(record)[LOG_TOPIC]]
    rows = [(t, m.name, m.file, m.line, m.DESCRIPTOR.enum_types_by_name["Level"]
             .values_by_number[m.level].name, m.message) for t, m in logs]
    assert rows == [
        (round(T0 * 1e9), "wf-42", "", 0, "INFO", "workflow PENDING"),
        (round((T0 + 1) * 1e9), "sim", "", 0, "INFO", "RUNNING: on node-a"),
        (round((T0 + 1.5) * 1e9), "sim", "sim/0/stdout", 1, "INFO", LOGS[0]["text"]),
        (round((T0 + 2) * 1e9), "sim", "sim/0/stderr", 1, "WARNING", LOGS[1]["text"]),
        (round((T0 + 4) * 1e9), "sim", "", 0, "INFO", "COMPLETED"),
        (round((T0 + 5) * 1e9), "train", "train/0/stdout", 1, "INFO", "step 1"),
        (round((T0 + 9.5) * 1e9), "wf-42", "", 0, "INFO", "workflow COMPLETED: all tasks done"),
    ]


def test_failures_and_retries_get_their_levels(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    events = [{"at": T0, "task": "sim", "retry": 0, "status": "RESCHEDULED", "message": "lost"},
              {"at": T0 + 1, "task": "sim", "retry": 1, "status": "FAILED", "message": "exit 3"}]
    lines = [{"ts": T0 + 0.5, "task": "sim", "retry": 1, "stream": "stdout", "text": "a"},
             {"ts": T0 + 0.6, "task": "sim", "retry": 1, "stream": "stdout", "text": "b"}]
    write_run_record(path, workflow=WORKFLOW, transitions=events, lineage=[], logs=lines)
    logs = [m for _, m in _decoded(path)[LOG_TOPIC]]
    level = logs[0].DESCRIPTOR.enum_types_by_name["Level"].values_by_number
    assert [(level[m.level].name, m.message, m.file, m.line) for m in logs] == [
        ("WARNING", "RESCHEDULED: lost", "", 0), ("INFO", "a", "sim/1/stdout", 1),
        ("INFO", "b", "sim/1/stdout", 2), ("ERROR", "FAILED (retry 1): exit 3", "", 0)]


def test_messages_carry_events_at_their_times(record: Path) -> None:
    with record.open("rb") as f:
        rows = [(c.topic, m.log_time, json.loads(m.data))
                for _, c, m in make_reader(f).iter_messages(topics=[STATUS_TOPIC])]
    assert [r[2]["status"] for r in rows] == ["PENDING", "RUNNING", "COMPLETED", "COMPLETED"]
    assert [r[1] for r in rows] == [round(t["at"] * 1e9) for t in TRANSITIONS]
    assert rows[1][2] == {k: TRANSITIONS[1][k] for k in
                          ("seq", "at", "workflow_id", "task", "retry", "status", "message")}


def test_lineage_channel_holds_one_message_per_attempt(record: Path) -> None:
    with record.open("rb") as f:
        rows = [(m.log_time, json.loads(m.data))
                for _, _, m in make_reader(f).iter_messages(topics=[LINEAGE_TOPIC])]
    assert [data["task"] for _, data in rows] == ["sim", "train"]
    assert rows[0][0] == round((T0 + 4) * 1e9)  # stamped at the attempt's end
    assert rows[1][1]["inputs"][0]["manifest"] == "sha256:" + "c" * 64
    assert rows[1][1]["plugin"] == "learn.act@0.2"


def test_logs_keep_unicode(record: Path) -> None:
    texts = [m.message for _, m in _decoded(record)[LOG_TOPIC] if m.file]
    assert texts == [line["text"] for line in LOGS]


def test_workflow_metadata_record(record: Path) -> None:
    with record.open("rb") as f:
        metadata = [(m.name, m.metadata) for m in make_reader(f).iter_metadata()]
    assert [name for name, _ in metadata] == ["osmo.workflow"]
    meta = metadata[0][1]
    assert (meta["id"], meta["name"], meta["status"]) == ("wf-42", "pendulum", "COMPLETED")
    assert float(meta["submitted_at"]) == T0 and float(meta["ended_at"]) == T0 + 9.5
    assert json.loads(meta["workflow"]) == WORKFLOW


def test_read_run_record_round_trip(record: Path) -> None:
    back = read_run_record(record)
    assert back["workflow"] == WORKFLOW
    assert back["lineage"] == LINEAGE
    assert [s["seq"] for s in back["status"]] == [1, 2, 3, 4]
    assert back["logs"] == _to_the_ns(LOGS)


def _to_the_ns(logs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Log lines as they read back: times kept to the nanosecond (a foxglove.Log timestamp)."""
    return [line | {"ts": round(line["ts"] * 1e9) / 1e9} for line in logs]


def _v1_record(path: Path, version: str = "1") -> None:
    """A run record as osmo wrote it before foxglove.Log: log lines as JSON on /osmo/logs."""
    with JsonMcapWriter(path) as out:
        status = out.add_json_channel(STATUS_TOPIC, "osmo.StatusTransition", {"type": "object"})
        lines = out.add_json_channel(LOGS_TOPIC, "osmo.LogLine", {"type": "object"})
        out.write(status, TRANSITIONS[0], round(T0 * 1e9))
        for line in LOGS:
            out.write(lines, line, round(line["ts"] * 1e9))
        out.add_metadata("osmo.workflow", {"record_version": version, "id": "wf-42",
                                           "name": "pendulum", "status": "COMPLETED",
                                           "submitted_at": repr(T0), "ended_at": ""})


def test_a_version_1_record_still_reads(tmp_path: Path) -> None:
    path = tmp_path / "old.mcap"
    _v1_record(path)
    back = read_run_record(path)
    assert back["logs"] == LOGS
    assert back["status"] == [TRANSITIONS[0]]
    assert back["workflow"]["id"] == "wf-42"


def test_a_record_of_a_newer_version_names_it(tmp_path: Path) -> None:
    path = tmp_path / "new.mcap"
    _v1_record(path, version="7")
    with pytest.raises(RecordError, match=r"run record version '7'.*reads versions 1, 2"):
        read_run_record(path)


def test_a_log_channel_of_another_schema_is_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "forged.mcap"
    with JsonMcapWriter(path) as out:
        log = out.add_json_channel(LOG_TOPIC, "osmo.LogLine", {"type": "object"})
        out.write(log, LOGS[0], round(T0 * 1e9))
        out.add_metadata("osmo.workflow", {"record_version": "2", "id": "wf-42"})
    with pytest.raises(RecordError, match=r"expected a foxglove.Log channel"):
        read_run_record(path)


def test_enum_statuses_and_defaults_are_accepted(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    workflow = WORKFLOW | {"status": WorkflowStatus.FAILED, "ended_at": None}
    events = [{"at": T0, "task": "sim", "retry": 0, "status": TaskStatus.FAILED}]
    write_run_record(path, workflow=workflow, transitions=events, lineage=[], logs=[])
    back = read_run_record(path)
    assert back["workflow"]["status"] == "FAILED" and back["workflow"]["ended_at"] is None
    assert back["status"] == [{"at": T0, "seq": None, "workflow_id": "wf-42", "task": "sim",
                               "retry": 0, "status": "FAILED", "message": ""}]


def test_empty_workflow_record_opens(tmp_path: Path) -> None:
    path = tmp_path / "empty.mcap"
    write_run_record(path, workflow=WORKFLOW, transitions=[], lineage=[], logs=[])
    assert read_run_record(path) == {"workflow": WORKFLOW, "status": [], "lineage": [], "logs": []}


def _bad_log() -> dict[str, Any]:
    return {"ts": T0 + 3, "task": "sim", "retry": 0, "stream": "stdout", "text": object()}


@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [
        ({"logs": [*LOGS, _bad_log()]}, "must be strings"),
        ({"logs": [LOGS[0] | {"retry": -1}]}, "retry an integer"),
        ({"logs": [{"ts": T0, "text": "x"}]}, "lacks task, retry, stream"),
        ({"logs": [LOGS[0] | {"ts": float("nan")}]}, "unix seconds"),
        ({"transitions": [*TRANSITIONS, {"at": T0, "message": "no status"}]}, "status"),
        ({"transitions": [{"at": -1.0, "status": "RUNNING"}]}, "unix seconds"),
        ({"lineage": [LINEAGE[0].to_dict()]}, "must be Lineage"),
        ({"workflow": WORKFLOW | {"extra": {1, 2}}}, "not JSON-serialisable"),
    ],
)
def test_a_failing_write_leaves_nothing_behind(
    tmp_path: Path, kwargs: dict[str, Any], needle: str
) -> None:
    path = tmp_path / "wf-42.mcap"
    args: dict[str, Any] = {"workflow": WORKFLOW, "transitions": TRANSITIONS,
                            "lineage": LINEAGE, "logs": LOGS} | kwargs
    with pytest.raises(UsageError, match=needle):
        write_run_record(path, **args)
    assert list(tmp_path.iterdir()) == []  # neither the file nor a temp file


def test_a_failing_rewrite_keeps_the_previous_file(record: Path) -> None:
    before = record.read_bytes()
    with pytest.raises(UsageError):
        write_run_record(record, workflow=WORKFLOW, transitions=TRANSITIONS, lineage=LINEAGE,
                         logs=[_bad_log()])
    assert record.read_bytes() == before
    assert list(record.parent.iterdir()) == [record]


def test_chunks_are_compressed_when_a_codec_is_installed(record: Path) -> None:
    with record.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.chunk_indexes
    expected = {mcapio.CompressionType.ZSTD: "zstd", mcapio.CompressionType.LZ4: "lz4",
                mcapio.CompressionType.NONE: ""}[mcapio._best_compression()]
    assert {c.compression for c in summary.chunk_indexes} == {expected}


def test_without_codecs_the_record_is_written_uncompressed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(mcapio._mcap_writer, "zstandard", None)
    monkeypatch.setattr(mcapio._mcap_writer, "lz4", None)
    path = tmp_path / "plain.mcap"
    write_run_record(path, workflow=WORKFLOW, transitions=TRANSITIONS, lineage=LINEAGE, logs=LOGS)
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    assert {c.compression for c in summary.chunk_indexes} == {""}
    assert read_run_record(path)["logs"] == _to_the_ns(LOGS)


def test_a_plain_mcap_is_not_a_run_record(tmp_path: Path) -> None:
    path = tmp_path / "plain.mcap"
    with LineageMcapWriter(path, None):
        pass
    with pytest.raises(RecordError, match="not an osmo run record"):
        read_run_record(path)
