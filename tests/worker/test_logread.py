"""Reading a log by position: bounded windows, newest first (tail), by time (since), and
damage that no writer makes."""

from __future__ import annotations

from pathlib import Path

import pytest

from osmo.worker.logread import end_position, newest_first, position_at, read_log, read_window
from osmo.worker.logs import LONGEST_RECORD, MAX_LINE, CappedFile, LogWriter, encode_records


def _log(tmp_path: Path, count: int, *, limit: int = 1 << 30, text: str = "line {n:06d}",
         ) -> Path:
    """A log of ``count`` records written at times 1000.0, 1000.5, 1001.0, ..."""
    log = tmp_path / "log.txt"
    capped = CappedFile(log, limit)
    for n in range(count):
        capped.append(encode_records(1000.0 + n / 2, "stdout", [text.format(n=n)]))
    capped.close()
    return log


@pytest.mark.parametrize("limit", [1 << 30, 20_000])  # without and with a marker
def test_windows_read_the_whole_log_a_bounded_piece_at_a_time(tmp_path: Path,
                                                              limit: int) -> None:
    log = _log(tmp_path, 3000, limit=limit)
    whole = read_log(log)[0]
    got, position, reads = [], 0, 0
    while True:
        window = read_window(log, position, 1000)
        assert len(window.records) == len(window.ends) and reads < 1000
        got += window.records
        position, reads = window.end, reads + 1
        if window.complete:
            break
    assert got == whole and reads >= log.stat().st_size // 1100
    assert position == end_position(log)
    for record, end in zip(window.records[:-1], window.ends[:-1], strict=True):
        assert read_window(log, end, 1).records[0].ts == record.ts + 0.5  # resume after it


def test_a_window_smaller_than_a_record_still_holds_it(tmp_path: Path) -> None:
    log = _log(tmp_path, 3, text="{n}" + "y" * MAX_LINE)
    window = read_window(log, 0, 10)
    assert len(window.records) == 1 and not window.complete


@pytest.mark.parametrize("limit", [1 << 30, 300_000])
@pytest.mark.parametrize("text", ["line {n:06d}", "{n} " + "z" * 30_000])  # long: many blocks
def test_newest_first_walks_back_with_positions_to_resume_from(tmp_path: Path, limit: int,
                                                               text: str) -> None:
    log = _log(tmp_path, 200, limit=limit, text=text)
    whole = read_log(log)[0]
    back = list(newest_first(log))
    assert [r for r, _ in back] == whole[::-1]
    for n in (1, 2, len(whole) // 2, len(whole)):
        start = back[n - 1][1]
        assert read_log(log, start)[0] == whole[-n:]  # the last n records, from there


def test_newest_first_skips_a_record_still_being_written(tmp_path: Path) -> None:
    log = _log(tmp_path, 5)
    with open(log, "ab") as f:
        f.write(b"1003.0\tstdout\thalf")
    assert [r.text for r, _ in newest_first(log)][:1] == ["line 000004"]


@pytest.mark.parametrize("limit", [1 << 30, 20_000])
def test_position_at_finds_the_first_record_since_a_time(tmp_path: Path, limit: int) -> None:
    log = _log(tmp_path, 3000, limit=limit)
    whole = read_log(log)[0]
    kept = [r for r in whole if r.stream == "stdout"]
    first, last = kept[0].ts, kept[-1].ts
    for since in (first + 0.25, first + 10.0, first + 10.1, last, last - 0.5):
        got = read_log(log, position_at(log, since))[0]
        assert got == [r for r in kept if r.ts >= since], since
    assert read_log(log, position_at(log, last + 1))[0] == []
    assert read_log(log, position_at(log, 0.0))[0] == whole  # the marker too, if any


def test_damage_longer_than_any_record_is_stepped_over(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    good = encode_records(1.0, "stdout", ["before"])
    log.write_bytes(good + b"x" * (LONGEST_RECORD + 10) + b"\n"
                    + encode_records(2.0, "stdout", ["after"]))
    assert [r.text for r in read_log(log)[0]] == ["before", "after"]
    assert [r.text for r, _ in newest_first(log)] == ["after", "before"]


def test_a_missing_log_reads_as_empty(tmp_path: Path) -> None:
    missing = tmp_path / "none.txt"
    assert read_window(missing, 5).records == [] and read_window(missing, 5).end == 5
    assert list(newest_first(missing)) == [] and end_position(missing) == 0
    assert position_at(missing, 1.0) == 0


def test_the_writer_and_readers_agree_on_escapes(tmp_path: Path) -> None:
    writer = LogWriter(tmp_path / "log.txt")
    writer.write("stdout", b"tab\there\nback\\slash\n")
    writer.close()
    texts = [r.text for r, _ in newest_first(tmp_path / "log.txt")]
    assert texts == ["back\\slash", "tab\there"]


def test_a_long_record_still_being_written_ends_the_window(tmp_path: Path) -> None:
    log = _log(tmp_path, 1)
    with open(log, "ab") as f:
        f.write(b"1003.0\tstdout\t" + b"w" * 5000)
    window = read_window(log, read_log(log)[1], 100)
    assert window.records == [] and window.complete
