r"""The attempt log format: one text record per line in ``log.txt``.

Each record is ``f"{time.time():.6f}\t{stream}\t{text}\n"`` where ``stream`` is ``stdout``,
``stderr`` or ``osmo`` (the orchestrator's own lines: image notes, kills, exit codes).

Rules the writer keeps so that one record is always exactly one line:

- ``text`` is escaped minimally: backslash → ``\\``, tab → ``\t``, newline → ``\n``,
  carriage return → ``\r``; ``read_log`` reverses it.
- Invalid UTF-8 is replaced (U+FFFD); a line longer than 64 KiB is split into several records
  (never inside a UTF-8 sequence).
- A partial last line (no trailing newline) is kept until more data arrives or the writer is
  closed, then written as its own record.
- Secret values given to the writer are replaced by ``****`` in every record, whatever its
  stream (``osmo.worker.masking``). A line is masked whole, before it is split at 64 KiB,
  and an unfinished line that must be cut keeps enough of its end for a value that starts
  there to be masked once the rest arrives.

The timestamp is taken when the bytes are read from the pipe, not when the program wrote them.
This module owns the format only; it does not know about processes or pipes.
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

from osmo.worker.masking import Masker

__all__ = ["MAX_LINE", "STREAMS", "LogRecord", "LogWriter", "read_log"]

MAX_LINE = 64 * 1024
STREAMS = ("stdout", "stderr", "osmo")

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
    """

    def __init__(self, path: Path, secrets: Iterable[str] = (),
                 sink: Callable[[bytes], None] | None = None) -> None:
        self.path = path
        self.sink = sink  # also gets every record as written (a remote worker streams them)
        self._masker = Masker(secrets)
        self._fd: int | None = None
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

    def flush_partial(self) -> None:
        """Write every stream's unfinished last line as a record of its own."""
        partial, self._partial = self._partial, {}
        for stream, rest in partial.items():
            self._append(stream, [self._masker.mask(rest).decode("utf-8", "replace")])

    def close(self) -> None:
        """Flush partial lines and close the file."""
        self.flush_partial()
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

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
        now = f"{time.time():.6f}"
        payload = "".join(f"{now}\t{stream}\t{_escape(t)}\n" for t in texts).encode()
        try:
            if self._fd is None:
                flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_CLOEXEC
                self._fd = os.open(self.path, flags, 0o644)
            os.write(self._fd, payload)
        except OSError as exc:  # a full disk loses log lines, never the attempt's report
            self.dropped += len(texts)
            _log.warning("cannot write %s: %s", self.path, exc)
        if self.sink is not None:
            self.sink(payload)


def _parse(line: str) -> LogRecord | None:
    parts = line.split("\t", 2)
    if len(parts) != 3:
        return None
    try:
        ts = float(parts[0])
    except ValueError:
        return None
    return LogRecord(ts, parts[1], _unescape(parts[2]))


def read_log(path: Path, offset: int = 0) -> tuple[list[LogRecord], int]:
    """Read the complete records of a log from byte ``offset`` on.

    Args:
        path: a ``log.txt``; a missing file reads as empty.
        offset: where a previous call stopped (0 for the start).

    Returns:
        the records and the offset to pass next time (to follow a growing log). A record
        whose line is still being written is left for the next call.
    """
    try:
        with open(path, "rb") as f:
            f.seek(offset)
            data = f.read()
    except FileNotFoundError:
        return [], offset
    end = data.rfind(b"\n") + 1
    records = []
    for raw in data[: end - 1].split(b"\n") if end else []:
        record = _parse(raw.decode("utf-8", "replace"))
        if record is not None:
            records.append(record)
    return records, offset + end


def image_note(image: str) -> str:
    """The osmo log line noting an ``image`` the process runtime does not use."""
    return f"image '{image}' recorded; the process runtime runs commands on the host"


def exit_note(code: int) -> str:
    """The osmo log line for an exit code (naming the signal for 128+N)."""
    if code > 128 and code - 128 in signal.Signals._value2member_map_:
        return f"exit code {code} ({signal.Signals(code - 128).name})"
    return f"exit code {code}"
