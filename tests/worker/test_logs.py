"""The log record format: one record per line, escapes, partial and long lines, follow, and
the cap: the oldest records dropped behind one marker, positions that survive it."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest

from osmo.worker.logread import read_log
from osmo.worker.logs import MAX_LINE, CappedFile, LogRecord, LogWriter, encode_records


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


# ------------------------------------------------------------------------------ the cap

DROPPED = re.compile(r"^([\d,]+) bytes of earlier output dropped \(log limit (.+)\)$")


def _capped(tmp_path: Path, limit: int, lines: int) -> tuple[Path, int]:
    """A writer capped at ``limit`` given ``lines`` numbered lines, a few per chunk; returns
    the log and the bytes of records it was given in all (counted at its sink)."""
    log = tmp_path / "log.txt"
    given: list[bytes] = []
    writer = LogWriter(log, sink=given.append, limit=limit)
    for start in range(0, lines, 7):
        writer.write("stdout", b"".join(b"line %06d\n" % n
                                        for n in range(start, min(lines, start + 7))))
    writer.close()
    return log, sum(map(len, given))


def test_past_the_cap_the_oldest_records_go_behind_one_marker(tmp_path: Path) -> None:
    log, given = _capped(tmp_path, 10_000, 5000)
    records = read_log(log)[0]
    marker = DROPPED.match(records[0].text)
    assert records[0].stream == "osmo" and marker is not None
    assert marker.group(2) == "10,000 bytes"
    first_line = log.read_bytes().split(b"\n", 1)[0] + b"\n"
    assert log.stat().st_size - len(first_line) <= 10_000
    assert int(marker.group(1).replace(",", "")) + log.stat().st_size - len(first_line) == given
    texts = [r.text for r in records[1:]]
    assert texts == [f"line {n:06d}" for n in range(5000 - len(texts), 5000)]
    assert len(texts) * 32 >= 10_000 // 2  # at least the newest half of the cap is kept
    assert records[0].ts == records[1].ts  # the marker sorts just before what it precedes
    assert not list(tmp_path.glob(".*"))  # no temporary file left


def test_the_marker_names_the_limit_in_mib(tmp_path: Path) -> None:
    log, _ = _capped(tmp_path, 1 << 20, 50_000)
    assert DROPPED.match(read_log(log)[0][0].text).group(2) == "1 MiB"  # type: ignore[union-attr]


def test_a_log_under_its_cap_has_no_marker(tmp_path: Path) -> None:
    log, given = _capped(tmp_path, 10_000, 100)
    assert log.stat().st_size == given
    assert read_log(log)[0][0].text == "line 000000"


def test_a_reopened_log_keeps_counting(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    total = 0
    for round_ in range(3):  # as the server reopens a remote attempt's log after evicting it
        capped = CappedFile(log, 4000)
        for n in range(200):
            payload = encode_records(float(n), "stdout", [f"round {round_} line {n:04d}"])
            capped.append(payload)
            total += len(payload)
        capped.close()
    first, _, rest = log.read_bytes().partition(b"\n")
    dropped = DROPPED.match(read_log(log)[0][0].text).group(1)  # type: ignore[union-attr]
    assert int(dropped.replace(",", "")) + len(rest) == total
    assert rest.endswith(b"round 2 line 0199\n")


def test_a_batch_larger_than_the_cap_keeps_its_newest_records(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    capped = CappedFile(log, 2000)
    capped.append(encode_records(1.0, "stdout", ["old"]))
    capped.append(encode_records(2.0, "stdout", [f"batch {n:04d}" for n in range(500)]))
    capped.close()
    records = read_log(log)[0]
    assert DROPPED.match(records[0].text)
    assert records[-1].text == "batch 0499" and "old" not in [r.text for r in records]
    assert log.stat().st_size <= 2000 + 100


def test_a_follower_keeps_its_place_across_the_rewrite(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    writer = LogWriter(log, limit=3000)
    seen: list[str] = []
    offset = 0
    for n in range(1000):
        writer.write("stdout", b"line %04d\n" % n)
        if n % 10 == 9:  # it keeps up: it misses nothing, sees nothing twice
            records, offset = read_log(log, offset)
            seen += [r.text for r in records]
    writer.close()
    assert seen == [f"line {n:04d}" for n in range(1000)]


def test_a_follower_that_fell_behind_sees_the_marker(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    writer = LogWriter(log, limit=3000)
    writer.write("stdout", b"first\n")
    offset = read_log(log)[1]
    writer.write("stdout", b"".join(b"line %04d\n" % n for n in range(1000)))
    writer.close()
    records, _ = read_log(log, offset)
    assert DROPPED.match(records[0].text) and records[-1].text == "line 0999"
