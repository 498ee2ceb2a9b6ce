"""Units: sizes, durations and exit-code lists, and their formatting round trips."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from osmo.spec.units import (
    format_duration,
    format_exit_codes,
    format_size,
    parse_duration,
    parse_exit_codes,
    parse_size,
)

KI, MI, GI, TI = 2**10, 2**20, 2**30, 2**40


@pytest.mark.parametrize(("text", "expected"), [
    (1024, 1024), ("0", 0), ("10B", 10), ("1K", KI), ("1Ki", KI), ("1KiB", KI),
    ("2M", 2 * MI), ("3Mi", 3 * MI), ("4G", 4 * GI), ("4Gi", 4 * GI), ("4GiB", 4 * GI),
    ("1T", TI), ("1.5Gi", 3 * GI // 2), (" 8 Gi ", 8 * GI),
])
def test_parse_size(text: object, expected: int) -> None:
    assert parse_size(text) == expected


@pytest.mark.parametrize("text", ["4GB", "4gb", "-1", -1, "1.5", "Gi", True, None, "1e3"])
def test_parse_size_rejects(text: object) -> None:
    with pytest.raises(ValueError):
        parse_size(text)


@pytest.mark.parametrize(("text", "expected"), [
    (90, 90), ("90", 90), ("45s", 45), ("30m", 1800), ("2h", 7200), ("1d", 86400),
])
def test_parse_duration(text: object, expected: int) -> None:
    assert parse_duration(text) == expected


@pytest.mark.parametrize(("text", "message"), [
    ("10h5m", "mixed units"), ("1.5h", "whole number"), ("0", "greater than zero"),
    ("5x", "whole number"), (True, "whole number"), ("-3s", "whole number"),
])
def test_parse_duration_rejects(text: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_duration(text)


@pytest.mark.parametrize(("value", "expected"), [
    (0, ((0, 0),)), ("0,1-10,16", ((0, 0), (1, 10), (16, 16))), ([3, "5-6"], ((3, 3), (5, 6))),
    (" 1 - 3 , 7", ((1, 3), (7, 7))),
])
def test_parse_exit_codes(value: object, expected: tuple[tuple[int, int], ...]) -> None:
    assert parse_exit_codes(value) == expected


@pytest.mark.parametrize(("value", "message"), [
    ("1-5,3", "listed twice"), ("5-1", "backwards"), ("a", "expected exit codes"),
    ("", "at least one"), ([], "at least one"), (-1, "negative"), (1.5, "expected"),
])
def test_parse_exit_codes_rejects(value: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_exit_codes(value)


@given(st.integers(min_value=0, max_value=2**50))
def test_size_round_trip(n: int) -> None:
    assert parse_size(format_size(n)) == n


@given(st.integers(min_value=1, max_value=10**9))
def test_duration_round_trip(n: int) -> None:
    assert parse_duration(format_duration(n)) == n


@given(st.lists(st.integers(0, 1000), unique=True, min_size=1, max_size=10))
def test_exit_codes_round_trip(points: list[int]) -> None:
    points.sort()
    ranges = tuple((points[i], points[i + 1] if i + 1 < len(points) else points[i])
                   for i in range(0, len(points), 2))
    assert parse_exit_codes(format_exit_codes(ranges)) == ranges
