"""Reading an attempt's log by position, a window at a time (the format: ``osmo.worker.logs``).

A *position* names a place in a log's whole output: the bytes of records written before it,
dropped ones included (``osmo.worker.logs`` drops the oldest records behind a marker when a
log passes its cap). A position therefore survives that rewrite: for a log that never passed
its cap it is the file offset, and afterwards it is the offset plus the bytes the marker
says were dropped, less the marker's own line. A position inside the dropped part reads as
the marker record, then the oldest record kept: a reader that fell behind learns what it
missed.

Nothing here holds a whole log: :func:`read_window` reads forward a bounded number of bytes,
:func:`newest_first` walks back from the end a block at a time (``--tail``), and
:func:`position_at` bisects for the first record at or after a time (``--since``; records
are written in time order). A line longer than any record the writer makes is damage and
is skipped.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from osmo.worker.logs import LONGEST_RECORD, LogRecord, Marker, marker_of, parse_record

__all__ = ["Window", "end_position", "newest_first", "position_at", "read_log", "read_window"]

_BLOCK = 64 << 10  # bytes read at a time going backwards


@dataclass
class Window:
    """What :func:`read_window` read.

    Attributes:
        records: the complete records read, oldest first (the marker first, if the window
            began in the dropped part).
        ends: the position just after each record (to resume after any of them).
        end: where the next read starts (after the last complete record, or past damage).
        complete: everything the file held was read (only a record still being written, if
            any, is left).
    """

    records: list[LogRecord] = field(default_factory=list)
    ends: list[int] = field(default_factory=list)
    end: int = 0
    complete: bool = True


class _Log:
    """An open log and its marker: positions ↔ file offsets."""

    def __init__(self, f: BinaryIO) -> None:
        self.f = f
        self.size = os.fstat(f.fileno()).st_size
        self.marker: Marker | None = marker_of(f)
        self.head = self.marker.length if self.marker else 0
        self.dropped = self.marker.dropped if self.marker else 0

    def offset(self, position: int) -> int:
        """The file offset of ``position`` (at least the first kept record's)."""
        return max(position - self.dropped, 0) + self.head

    def position(self, offset: int) -> int:
        """The position of file offset ``offset`` (past the marker)."""
        return offset - self.head + self.dropped


def _open(path: Path) -> BinaryIO | None:
    try:
        return open(path, "rb")
    except FileNotFoundError:
        return None


def read_window(path: Path, position: int = 0, size: int = 1 << 20) -> Window:
    """The complete records from ``position`` on, reading about ``size`` bytes at most.

    A window holds at least one record when one is there: a record longer than ``size`` is
    read whole (up to :data:`~osmo.worker.logs.LONGEST_RECORD`). A missing file reads as
    empty.
    """
    f = _open(path)
    if f is None:
        return Window(end=position)
    with f:
        log = _Log(f)
        window = Window(end=position)
        if log.marker is not None and position < log.dropped:
            window.records.append(log.marker.record)
            window.ends.append(log.dropped)
            window.end = position = log.dropped
        start = log.offset(position)
        data = os.pread(f.fileno(), max(size, 1), start)
        if b"\n" not in data and start + len(data) < log.size:  # a record longer than size
            data = os.pread(f.fileno(), LONGEST_RECORD, start)
            newline = data.find(b"\n")
            if newline < 0 and start + len(data) < log.size:  # damage: step over it
                window.end = position + len(data)
                window.complete = False
                return window
            data = data[:newline + 1] if newline >= 0 else data
        last = data.rfind(b"\n") + 1
        at = position
        for line in data[:last - 1].split(b"\n") if last else ():
            at += len(line) + 1
            record = parse_record(line)
            if record is not None:
                window.records.append(record)
                window.ends.append(at)
        window.end = position + last
        window.complete = start + len(data) >= log.size
        return window


def read_log(path: Path, offset: int = 0) -> tuple[list[LogRecord], int]:
    """Every complete record from position ``offset`` on, and the position to pass next time.

    For small logs and tests: this holds them all.
    """
    records: list[LogRecord] = []
    while True:
        window = read_window(path, offset)
        records += window.records
        offset = window.end
        if window.complete:
            return records, offset


def end_position(path: Path) -> int:
    """The position after the last complete record (0 for a missing file)."""
    f = _open(path)
    if f is None:
        return 0
    with f:
        log = _Log(f)
        return log.position(_complete_end(log))


def newest_first(path: Path) -> Iterator[tuple[LogRecord, int]]:
    """The log's complete records from the newest back, each with its starting position.

    The marker, if any, comes last (its position, 0, reads as the marker). A block at a time:
    stopping early reads only the end of the file.
    """
    f = _open(path)
    if f is None:
        return
    with f:
        log = _Log(f)
        end = _complete_end(log)
        tail = b""  # the end of a line that starts in an earlier block, with its newline
        while end > log.head:
            start = max(log.head, end - _BLOCK)
            data = os.pread(f.fileno(), end - start, start) + tail
            end = start
            lines = data.split(b"\n")
            first = 1 if start > log.head else 0
            tail = lines[0] + b"\n" if first and len(lines[0]) <= LONGEST_RECORD else b""
            newline = start + len(data) - len(lines[-1]) - 1  # (lines[-1]: b"" or damage)
            for line in reversed(lines[first:-1]):
                begin = newline - len(line)
                record = parse_record(line) if line else None
                if record is not None:
                    yield record, log.position(begin)
                newline = begin - 1
        if log.marker is not None:
            yield log.marker.record, 0


def position_at(path: Path, since: float) -> int:
    """The position of the first record written at or after ``since`` (epoch seconds).

    Found by bisection; the end when there is none, 0 when it is the first kept one (a read
    from there shows the marker too).
    """
    f = _open(path)
    if f is None:
        return 0
    with f:
        log = _Log(f)
        # Records starting before low are older than since; the record at high (or the
        # file's end) is not. Both are where lines start.
        low, high = log.head, log.size
        while low < high:
            middle = (low + high) // 2
            start = low if middle == low else _next_line(log, middle - 1)
            if start >= high:  # no line starts in [middle, high): decide on low's
                start = low
            record = _record_at(log, start)
            if record is not None and record.ts >= since:
                high = start
            else:
                low = _next_line(log, start)
        return 0 if low <= log.head else log.position(low)


def _complete_end(log: _Log) -> int:
    """The file offset after its last complete record (the marker's end if none)."""
    reach = min(log.size - log.head, LONGEST_RECORD)
    data = os.pread(log.f.fileno(), reach, log.size - reach)
    return max(log.size - reach + data.rfind(b"\n") + 1, log.head)


def _record_at(log: _Log, offset: int) -> LogRecord | None:
    """The record of the line at ``offset`` (None: damage, or a line still being written)."""
    data = os.pread(log.f.fileno(), LONGEST_RECORD, offset)
    newline = data.find(b"\n")
    return None if newline < 0 else parse_record(data[:newline])


def _next_line(log: _Log, offset: int) -> int:
    """The offset after the first newline at or after ``offset`` (the file's size if none)."""
    data = os.pread(log.f.fileno(), LONGEST_RECORD, offset)
    newline = data.find(b"\n")
    return log.size if newline < 0 else offset + newline + 1
