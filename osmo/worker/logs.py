r"""The attempt log format: one text record per line in ``log.txt``.

Each record is ``f"{time.time():.6f}\t{stream}\t{text}\n"`` where ``stream`` is ``stdout``,
``stderr`` or ``osmo`` (the orchestrator's own lines: image notes, kills, exit codes).

Rules the writer keeps so that one record is always exactly one line:

- ``text`` is escaped minimally: backslash → ``\\``, tab → ``\t``, newline → ``\n``,
  carriage return → ``\r``; :func:`parse_record` reverses it.
- Invalid UTF-8 is replaced (U+FFFD); a line longer than 64 KiB is split into several records
  (never inside a UTF-8 sequence).
- A partial last line (no trailing newline) is kept until more data arrives or the writer is
  closed, then written as its own record.
- Secret values given to the writer are replaced by ``****`` in every record, whatever its
  stream (``osmo.worker.masking``). A line is masked whole, before it is split at 64 KiB,
  and an unfinished line that must be cut keeps enough of its end for a value that starts
  there to be masked once the rest arrives.

The timestamp is taken when the bytes are read from the pipe, not when the program wrote them.

The cap. A log holds at most ``limit`` bytes of records (64 MiB unless ``--log-limit`` of
``osmo server`` or ``osmo worker`` says otherwise: ``osmo.options``). When an append would
pass it, the oldest records are dropped, as the kubelet's log rotation does (the newest output
is what a user needs): :class:`CappedFile` rewrites the file (temp + rename) with the newest
half of the limit behind one marker record, always the file's first line::

    <time>\tosmo\t123,456,789 bytes of earlier output dropped (log limit 64 MiB)

whose count is every byte of records dropped so far. A stored log is then never larger than
the limit plus that line, and the cap costs one (kernel) copy of half the limit per half the
limit written: about one byte copied per byte logged, and nothing per line.
:func:`marker_of` reads the marker back (``osmo.worker.logread`` reads logs by position).

This module owns the format and the writing; it does not know about processes or pipes.
"""

from __future__ import annotations

import logging
import os
import re
import signal
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from osmo.options import DEFAULT_LOG_LIMIT
from osmo.worker.masking import Masker

__all__ = ["LONGEST_RECORD", "MAX_LINE", "STREAMS", "CappedFile", "LogRecord", "LogWriter",
           "Marker", "encode_records", "marker_of", "parse_record"]

MAX_LINE = 64 * 1024
STREAMS = ("stdout", "stderr", "osmo")
LONGEST_RECORD = 4 * MAX_LINE
"""No record the writer makes is longer (a 64 KiB line of invalid bytes, each replaced by
3-byte U+FFFD, plus its time and stream); a reader treats a longer "line" as damage."""

_log = logging.getLogger(__name__)

_ESCAPES = {"\\": "\\\\", "\t": "\\t", "\n": "\\n", "\r": "\\r"}
_ESCAPE_RE = re.compile(r"[\\\t\n\r]")
_UNESCAPES = {"\\": "\\", "t": "\t", "n": "\n", "r": "\r"}
_UNESCAPE_RE = re.compile(r"\\(.)")


@dataclass(frozen=True)
class LogRecord:
    """One log line: wall-clock time (seconds since the epoch), stream name and text."""

    ts: float
    stream: str
    text: str


def encode_records(ts: float, stream: str, texts: Iterable[str]) -> bytes:
    """Records of ``texts`` (escaped), all stamped ``ts``, as the log file holds them."""
    now = f"{ts:.6f}"
    return "".join(f"{now}\t{stream}\t{_escape(t)}\n" for t in texts).encode()


def parse_record(line: bytes) -> LogRecord | None:
    """The record of one log line (without its newline); None if it is not one."""
    parts = line.decode("utf-8", "replace").split("\t", 2)
    if len(parts) != 3:
        return None
    try:
        ts = float(parts[0])
    except ValueError:
        return None
    return LogRecord(ts, parts[1], _unescape(parts[2]))


def _escape(text: str) -> str:
    return _ESCAPE_RE.sub(lambda m: _ESCAPES[m.group(0)], text)


def _unescape(text: str) -> str:
    if "\\" not in text:
        return text
    return _UNESCAPE_RE.sub(lambda m: _UNESCAPES.get(m.group(1), m.group(1)), text)


def _utf8_cut(data: bytes, limit: int) -> int:
    """An index ≤ ``limit`` that does not fall inside a UTF-8 multi-byte sequence."""
    cut = limit
    while cut > limit - 3 and cut > 0 and (data[cut] & 0xC0) == 0x80:
        cut -= 1
    return cut if cut > 0 else limit


class LogWriter:
    """Appends records for one attempt to ``path`` (opened lazily, on the first record).

    Not thread-safe: one attempt's writer is used by one thread (the pool's I/O thread).
    Write errors (a full disk) drop records and count them in ``dropped``; they never raise.

    Args:
        path: the log file.
        secrets: values to mask as ``****`` in every record (see the module docstring).
        sink: also gets every record as written, before the cap (a remote worker streams
            them to the server, which caps its own copy).
        limit: the cap on the file (see the module docstring).
    """

    def __init__(self, path: Path, secrets: Iterable[str] = (),
                 sink: Callable[[bytes], None] | None = None, *,
                 limit: int = DEFAULT_LOG_LIMIT) -> None:
        self.path = path
        self.sink = sink
        self._masker = Masker(secrets)
        self._file = CappedFile(path, limit)
        self._partial: dict[str, bytes] = {}
        self.dropped = 0  # records that could not be written (e.g. disk full)

    def write(self, stream: str, data: bytes) -> None:
        """Record the complete lines in ``data`` (a chunk read from ``stream``'s pipe)."""
        buffer = self._partial.pop(stream, b"") + data
        lines: list[bytes] = []
        start = 0
        while (end := buffer.find(b"\n", start)) >= 0:
            lines.extend(self._split_long(self._masker.mask(buffer[start:end])))
            start = end + 1
        rest = buffer[start:]
        if len(rest) > MAX_LINE:  # an unfinished line too long to keep: cut it
            rest = self._masker.mask(rest)
            hold = min(self._masker.hold, MAX_LINE // 2)  # a value may start in the last bytes
            while len(rest) > MAX_LINE:
                cut = _utf8_cut(rest, min(MAX_LINE, len(rest) - hold))
                lines.append(rest[:cut])
                rest = rest[cut:]
        if rest:
            self._partial[stream] = rest
        if lines:
            self._append(stream, [line.decode("utf-8", "replace") for line in lines])

    def line(self, stream: str, text: str) -> None:
        """Record one line of text, secrets masked (used for ``osmo`` lines)."""
        self._append(stream, [self._masker.mask_text(text)])

    def pending(self, stream: str) -> int:
        """Bytes of ``stream``'s unfinished last line, held back until its end comes."""
        return len(self._partial.get(stream, b""))

    def flush_partial(self) -> None:
        """Write every stream's unfinished last line as a record of its own."""
        partial, self._partial = self._partial, {}
        for stream, rest in partial.items():
            self._append(stream, [self._masker.mask(rest).decode("utf-8", "replace")])

    def close(self) -> None:
        """Flush partial lines and close the file."""
        self.flush_partial()
        self._file.close()

    @staticmethod
    def _split_long(line: bytes) -> list[bytes]:
        parts: list[bytes] = []
        while len(line) > MAX_LINE:
            cut = _utf8_cut(line, MAX_LINE)
            parts.append(line[:cut])
            line = line[cut:]
        parts.append(line)
        return parts

    def _append(self, stream: str, texts: list[str]) -> None:
        payload = encode_records(time.time(), stream, texts)
        try:
            self._file.append(payload)
        except OSError as exc:  # a full disk loses log lines, never the attempt's report
            self.dropped += len(texts)
            _log.warning("cannot write %s: %s", self.path, exc)
        if self.sink is not None:
            self.sink(payload)


@dataclass(frozen=True)
class Marker:
    """A log's first line when records were dropped: how many bytes, and its own length."""

    dropped: int
    length: int
    record: LogRecord


_MARKER_RE = re.compile(rb"(\d{1,12}\.\d{1,9})\tosmo\t(([\d,]{1,25}) bytes of earlier output "
                        rb"dropped \(log limit [^)\n]{1,24}\))\n")
_MOST_DROPPED = 2**53  # a count above this is no marker this module wrote


def marker_of(f: BinaryIO) -> Marker | None:
    """The marker at the start of open log ``f`` (None: nothing was dropped).

    Reads the file's first line with ``pread``: ``f``'s position does not move.
    """
    match = _MARKER_RE.match(os.pread(f.fileno(), 200, 0))
    if match is None:
        return None
    dropped = int(match.group(3).replace(b",", b""))
    if not 0 < dropped <= _MOST_DROPPED:
        return None
    record = LogRecord(float(match.group(1)), "osmo", match.group(2).decode())
    return Marker(dropped, match.end(), record)


def _marker_line(ts: float, dropped: int, limit: int) -> bytes:
    shown = f"{limit >> 20} MiB" if limit % (1 << 20) == 0 else f"{limit:,} bytes"
    return encode_records(ts, "osmo", [
        f"{dropped:,} bytes of earlier output dropped (log limit {shown})"])


class CappedFile:
    """Appends whole records to one log file, keeping at most ``limit`` bytes of them.

    See the module docstring. Opened on the first append. Not thread-safe.

    Args:
        path: the log file (an existing one is appended to, its marker honoured).
        limit: bytes of records to keep at most.
    """

    def __init__(self, path: Path, limit: int = DEFAULT_LOG_LIMIT) -> None:
        self.path = path
        self.limit = limit
        self._fd: int | None = None
        self._size = 0  # bytes in the file, marker included
        self._head = 0  # bytes of the marker line (0: none)
        self._dropped = 0  # bytes of records dropped before the first kept one

    def append(self, payload: bytes) -> None:
        """Append ``payload`` (whole records), dropping the oldest records if it must.

        Raises:
            OSError: the file cannot be opened, rewritten or written.
        """
        if self._fd is None:
            self._open()
        if self._size - self._head + len(payload) > self.limit:
            payload = self._make_room(payload)
        assert self._fd is not None
        self._size += os.write(self._fd, payload)

    def close(self) -> None:
        """Close the file (a later append opens it again)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def _open(self) -> None:
        flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_CLOEXEC
        self._fd = os.open(self.path, flags, 0o644)
        self._size = os.fstat(self._fd).st_size
        marker = None
        if self._size:  # a new log (an attempt's first record) has no marker to read
            with open(self.path, "rb") as f:
                marker = marker_of(f)
        self._head = marker.length if marker else 0
        self._dropped = marker.dropped if marker else 0

    def _make_room(self, payload: bytes) -> bytes:
        """Drop the oldest records so that ``payload`` fits; return what of it to write."""
        lost = 0
        if len(payload) > self.limit:  # one batch larger than the whole cap: its newest part
            lost = _line_start(payload, len(payload) - self.limit)
            payload = payload[lost:]
        keep = min(self.limit // 2, self.limit - len(payload))
        with open(self.path, "rb") as f:
            start = max(self._head, self._size - keep)
            if start > self._head:  # the first whole record from there
                newline = os.pread(f.fileno(), LONGEST_RECORD, start - 1).find(b"\n")
                start += max(newline, 0)  # (none: a damaged stretch, cut anywhere)
            self._rewrite(f, start, lost)
        return payload

    def _rewrite(self, f: BinaryIO, start: int, lost: int) -> None:
        """Replace the file by a marker and its bytes from ``start`` on (temp + rename)."""
        dropped = self._dropped + start - self._head + lost
        f.seek(start)
        first = parse_record(f.readline(LONGEST_RECORD).rstrip(b"\n"))
        marker = _marker_line(first.ts if first else time.time(), dropped, self.limit)
        tmp = self.path.with_name(f".{self.path.name}.tmp")
        tmp.unlink(missing_ok=True)  # a crashed rewrite's; O_EXCL then never follows a link
        out = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644)
        try:
            os.write(out, marker)
            _copy(f.fileno(), out, start, self._size - start)
            os.replace(tmp, self.path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        finally:
            os.close(out)
        self.close()
        self._open()


def _line_start(data: bytes, at: int) -> int:
    """Where the first record at or after ``at`` (> 0) starts in ``data``."""
    newline = data.find(b"\n", at - 1)
    return len(data) if newline < 0 else newline + 1


def _copy(src: int, dst: int, offset: int, count: int) -> None:
    """Copy ``count`` bytes of ``src`` from ``offset`` to the end of ``dst``, in the kernel."""
    while count > 0:
        try:
            n = os.copy_file_range(src, dst, count, offset)
        except OSError:  # a filesystem without it: through user space
            n = os.write(dst, os.pread(src, min(count, 1 << 20), offset))
        if n == 0:
            return  # the file is shorter than it was (never, with one writer)
        offset += n
        count -= n



def exit_note(code: int) -> str:
    """The osmo log line for an exit code (naming the signal for 128+N)."""
    if code > 128 and code - 128 in signal.Signals._value2member_map_:
        return f"exit code {code} ({signal.Signals(code - 128).name})"
    return f"exit code {code}"
