"""Units of the spec: sizes to bytes, durations to seconds, exit-code lists to ranges, and back.

Pure functions. Parsers raise ``ValueError`` whose message says what is accepted; callers add
the source position. Formatters produce text the parsers read back to the same value.
"""

from __future__ import annotations

import re
from decimal import Decimal
from typing import Any

__all__ = [
    "SIZE_UNITS",
    "format_duration",
    "format_exit_codes",
    "format_size",
    "overlap",
    "parse_duration",
    "parse_exit_codes",
    "parse_size",
]

_KI = 1024
#: Every accepted size unit and its factor. All binary: ``G`` means ``Gi`` (OSMO semantics).
SIZE_UNITS: dict[str, int] = {"": 1, "B": 1}
for _power, _letter in enumerate("KMGT", start=1):
    for _suffix in (_letter, _letter + "i", _letter + "iB"):
        SIZE_UNITS[_suffix] = _KI**_power

_SIZE_RE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([A-Za-z]*)\s*$")
_DURATION_RE = re.compile(r"^\s*(\d+)\s*([smhd]?)\s*$")
_MIXED_RE = re.compile(r"^\s*(\d+(?:\.\d+)?[smhd]){2,}\s*$")
_SECONDS = {"": 1, "s": 1, "m": 60, "h": 3600, "d": 86400}
_SIZE_HELP = "a number with an optional unit B, K/Ki/KiB, M/Mi/MiB, G/Gi/GiB or T/Ti/TiB"


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def parse_size(value: Any) -> int:
    """``"4Gi"``, ``"512M"``, ``1024`` → bytes (units are binary; no unit means bytes)."""
    if _is_int(value):
        if value < 0:
            raise ValueError("a size cannot be negative")
        return int(value)
    match = _SIZE_RE.match(value) if isinstance(value, str) else None
    if match is None:
        raise ValueError(f"expected {_SIZE_HELP}, like '4Gi'; got {value!r}")
    number, unit = match.groups()
    if unit not in SIZE_UNITS:
        raise ValueError(f"unknown size unit {unit!r} in {value!r}; use {_SIZE_HELP}")
    total = Decimal(number) * SIZE_UNITS[unit]
    if total != total.to_integral_value():
        raise ValueError(f"{value!r} is not a whole number of bytes")
    return int(total)


def format_size(n: int) -> str | int:
    """Bytes as the largest exact binary unit (``4294967296`` → ``"4Gi"``), else the int."""
    for unit in ("Ti", "Gi", "Mi", "Ki"):
        factor = SIZE_UNITS[unit]
        if n and n % factor == 0:
            return f"{n // factor}{unit}"
    return n


def parse_duration(value: Any) -> int:
    """``"30m"``, ``"2h"``, ``"1d"``, ``"45s"`` or a bare number (seconds) → seconds > 0."""
    if _is_int(value):
        seconds = int(value)
    else:
        text = value if isinstance(value, str) else ""
        match = _DURATION_RE.match(text)
        if match is None:
            if _MIXED_RE.match(text):
                raise ValueError(f"mixed units in {value!r} are not supported; write one "
                                 "number and one unit, e.g. '605m' instead of '10h5m'")
            raise ValueError(f"expected a whole number with an optional unit s, m, h or d, "
                             f"like '30m'; got {value!r}")
        seconds = int(match.group(1)) * _SECONDS[match.group(2)]
    if seconds <= 0:
        raise ValueError("a timeout must be greater than zero")
    return seconds


def format_duration(seconds: float) -> str:
    """Seconds as ``"<n>s"``."""
    if float(seconds).is_integer():
        return f"{int(seconds)}s"
    return f"{seconds}s"


def _parse_code_item(item: Any) -> tuple[int, int]:
    if _is_int(item):
        low = high = int(item)
    elif isinstance(item, str) and re.fullmatch(r"\s*\d+\s*(-\s*\d+\s*)?", item):
        parts = [int(p) for p in item.split("-")]
        low, high = parts[0], parts[-1]
    else:
        raise ValueError(f"expected exit codes like '0,1-10,16'; got {item!r}")
    if low < 0:
        raise ValueError("exit codes cannot be negative")
    if low > high:
        raise ValueError(f"range {low}-{high} runs backwards; write {high}-{low}")
    return low, high


def parse_exit_codes(value: Any) -> tuple[tuple[int, int], ...]:
    """``"0,1-10,16"``, ``3`` or ``[0, "2-5"]`` → inclusive ranges, in the order written.

    Raises:
        ValueError: on a malformed item or ranges that overlap each other.
    """
    if isinstance(value, list):
        items: list[Any] = value
    elif isinstance(value, str):
        items = value.split(",")
    else:
        items = [value]
    if not items or items == [""]:
        raise ValueError("expected at least one exit code, like '0,1-10,16'")
    ranges = tuple(_parse_code_item(item) for item in items)
    clash = overlap(ranges, ranges)
    if clash:
        raise ValueError(f"exit codes {clash} are listed twice")
    return ranges


def overlap(a: tuple[tuple[int, int], ...], b: tuple[tuple[int, int], ...]) -> str | None:
    """A description of the first overlap between two range lists, or None.

    A range with itself is ignored when ``a is b``.
    """
    for i, (lo1, hi1) in enumerate(a):
        for j, (lo2, hi2) in enumerate(b):
            if a is b and i >= j:
                continue
            if lo1 <= hi2 and lo2 <= hi1:
                low, high = max(lo1, lo2), min(hi1, hi2)
                return str(low) if low == high else f"{low}-{high}"
    return None


def format_exit_codes(ranges: tuple[tuple[int, int], ...]) -> str:
    """Ranges as ``"0,1-10,16"``."""
    return ",".join(str(lo) if lo == hi else f"{lo}-{hi}" for lo, hi in ranges)
