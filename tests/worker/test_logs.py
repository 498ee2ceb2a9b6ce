"""The log record format: one record per line, escapes, partial and long lines, follow."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from osmo.worker.logs import MAX_LINE, LogRecord, LogWriter, read_log


def texts(path: Path) -> list[tuple[str, str]]:
    return [(r.stream, r.text) for r in read_log(path)[0]]


def test_records_have_time_stream_and_text(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    before = time.time()
    writer = LogWriter(log)
    writer.write("stdout", b"one\ntwo\n")
    writer.write("stderr", b"oops\n")
    writer.line("osmo", "exit code 0")
    writer.close()
    after = time.time()
    records, offset = read_log(log)
    assert [(r.stream, r.text) for r in records] == [
        ("stdout", "one"),
        ("stdout", "two"),
        ("stderr", "oops"),
        ("osmo", "exit code 0"),
    ]
    assert all(before - 1e-3 <= r.ts <= after + 1e-3 for r in records)
    assert offset == log.stat().st_size
    first = log.read_text().splitlines()[0]
    assert first.split("\t")[1:] == ["stdout", "one"]
    assert len(first.split("\t")[0].split(".")[1]) == 6


def test_no_file_until_first_record(tmp_path: Path) -> None:
    writer = LogWriter(tmp_path / "log.txt")
    writer.close()
    assert not (tmp_path / "log.txt").exists()
    assert read_log(tmp_path / "log.txt") == ([], 0)


def test_partial_lines_join_across_chunks_and_flush_at_close(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    writer = LogWriter(log)
    writer.write("stdout", b"hel")
    writer.write("stderr", b"e")
    writer.write("stdout", b"lo\nwor")
    assert texts(log) == [("stdout", "hello")]
    writer.close()
    assert sorted(texts(log)) == [("stderr", "e"), ("stdout", "hello"), ("stdout", "wor")]


@pytest.mark.parametrize(
    "text", ["tab\there", "back\\slash", "cr\rlf", "\\n literal", "ünïcødé ✓", "", "\\t\t\\"]
)
def test_escapes_round_trip(tmp_path: Path, text: str) -> None:
    log = tmp_path / "log.txt"
    writer = LogWriter(log)
    writer.line("osmo", text)
    writer.line("osmo", "multi\nline")
    writer.close()
    assert texts(log) == [("osmo", text), ("osmo", "multi\nline")]
    assert len(log.read_bytes().splitlines()) == 2


def test_invalid_utf8_is_replaced(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    writer = LogWriter(log)
    writer.write("stdout", b"ok \xff\xfe end\n")
    writer.close()
    assert texts(log) == [("stdout", "ok \ufffd\ufffd end")]


def test_long_lines_are_split(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    writer = LogWriter(log)
    writer.write("stdout", b"x" * (MAX_LINE * 2 + 10) + b"\n")
    for _ in range(3):  # without a newline, arriving in pieces
        writer.write("stderr", b"y" * MAX_LINE)
    writer.close()
    records = texts(log)
    assert [len(t) for s, t in records if s == "stdout"] == [MAX_LINE, MAX_LINE, 10]
    assert sum(len(t) for s, t in records if s == "stderr") == 3 * MAX_LINE
    assert all(len(t) <= MAX_LINE for _, t in records)


def test_long_lines_split_between_utf8_characters(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    writer = LogWriter(log)
    text = "a" + "é" * MAX_LINE  # 2-byte characters, misaligned by one byte
    writer.write("stdout", text.encode() + b"\n")
    writer.close()
    records = texts(log)
    assert "\ufffd" not in "".join(t for _, t in records)
    assert "".join(t for _, t in records) == text


def test_follow_with_offsets(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    writer = LogWriter(log)
    writer.write("stdout", b"a\n")
    records, offset = read_log(log)
    assert records == [LogRecord(records[0].ts, "stdout", "a")]
    assert read_log(log, offset) == ([], offset)
    writer.write("stdout", b"b\nc\n")
    more, offset2 = read_log(log, offset)
    assert [r.text for r in more] == ["b", "c"]
    assert offset2 > offset
    writer.close()


def test_follow_leaves_a_half_written_record(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    log.write_bytes(b"1.000000\tstdout\tdone\n2.000000\tstdout\tpart")
    records, offset = read_log(log)
    assert records == [LogRecord(1.0, "stdout", "done")]
    with open(log, "ab") as f:
        f.write(b"ial\n")
    assert read_log(log, offset) == ([LogRecord(2.0, "stdout", "partial")], log.stat().st_size)


def test_malformed_lines_are_skipped(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    log.write_bytes(b"garbage\nnot-a-time\tstdout\tx\n3.5\tstderr\tfine\n")
    assert read_log(log)[0] == [LogRecord(3.5, "stderr", "fine")]


def test_unwritable_log_drops_records_without_raising(tmp_path: Path) -> None:
    writer = LogWriter(tmp_path / "missing-folder" / "log.txt")
    writer.write("stdout", b"lost\n")
    writer.line("osmo", "lost too")
    writer.close()
    assert writer.dropped == 2
