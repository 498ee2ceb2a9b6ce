"""Secret values are masked in every log record: split reads, long lines, overlaps, osmo lines."""

from __future__ import annotations

from pathlib import Path

import pytest

from osmo.worker.logread import read_log
from osmo.worker.logs import MAX_LINE, LogWriter
from osmo.worker.masking import Masker

SECRET = "hunter2-s3cr3t"


def texts(path: Path) -> list[tuple[str, str]]:
    return [(r.stream, r.text) for r in read_log(path)[0]]


@pytest.mark.parametrize(("values", "data", "masked"), [
    ([SECRET], f"pw={SECRET}!", "pw=****!"),
    ([SECRET], f"{SECRET}{SECRET} {SECRET}", "**** ****"),  # touching occurrences: one mask
    (["abcd", "cdef"], "xabcdefx", "x****x"),  # overlapping values: nothing of either leaks
    (["aaaa"], "aaaaaa", "****"),  # overlapping occurrences of one value
    (["abcd", "abcdef"], "abcdefgh abcdx", "****gh ****x"),  # one value inside another
    (["ünï©ødé"], "a ünï©ødé b", "a **** b"),
    (["-----BEGIN KEY-----\nAAAAbbbb\n"], "AAAAbbbb", "****"),  # each line of a long value
    (["ab"], "a b ab abc", "a b **** ****c"),  # short values too (see the caveat)
    ([""], "empty values mask nothing", "empty values mask nothing"),
    ([], f"{SECRET}", SECRET),
])
def test_masker(values: list[str], data: str, masked: str) -> None:
    assert Masker(values).mask_text(data) == masked
    assert Masker(values).mask(data.encode()) == masked.encode()


def test_values_split_across_reads_are_masked(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    writer = LogWriter(log, [SECRET, "other-value"])
    data = f"token {SECRET} and other-value\nnext {SECRET}".encode()
    for i in range(len(data)):  # one byte per pipe read, on both streams
        writer.write("stdout", data[i:i + 1])
        writer.write("stderr", data[i:i + 1])
    writer.close()
    assert texts(log) == [("stdout", "token **** and ****"), ("stderr", "token **** and ****"),
                          ("stdout", "next ****"), ("stderr", "next ****")]
    assert SECRET.encode() not in log.read_bytes()


def test_osmo_lines_are_masked(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    writer = LogWriter(log, [SECRET])
    writer.line("osmo", f"start failed: no file {SECRET}")
    writer.close()
    assert texts(log) == [("osmo", "start failed: no file ****")]


@pytest.mark.parametrize("where", [MAX_LINE - 3, MAX_LINE - len(SECRET) + 1, MAX_LINE])
def test_value_straddling_the_long_line_cut_is_masked(tmp_path: Path, where: int) -> None:
    log = tmp_path / "log.txt"
    writer = LogWriter(log, [SECRET])
    line = b"x" * where + SECRET.encode() + b"y" * 100
    writer.write("stdout", line + b"\n")  # a complete long line
    writer.write("stderr", line[:MAX_LINE + 2])  # an unfinished one, cut before its end
    writer.write("stderr", line[MAX_LINE + 2:])
    writer.close()
    assert SECRET.encode() not in log.read_bytes()
    for stream in ("stdout", "stderr"):
        joined = "".join(t for s, t in texts(log) if s == stream)
        assert joined == "x" * where + "****" + "y" * 100
    assert all(len(t.encode()) <= MAX_LINE for _, t in texts(log))


def test_unfinished_line_far_longer_than_the_limit(tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    writer = LogWriter(log, [SECRET])
    chunk = (b"z" * 1000 + SECRET.encode()) * 200  # no newline at all, in 64 KiB reads
    for i in range(0, len(chunk), 65536):
        writer.write("stdout", chunk[i:i + 65536])
    writer.close()
    joined = "".join(t for _, t in texts(log))
    assert joined == ("z" * 1000 + "****") * 200


@pytest.mark.parametrize("prefix", [b"", b"a", b"ab", b"user:", b'{"k": "'])
@pytest.mark.parametrize("urlsafe", [False, True])
def test_base64_forms_are_masked_at_any_offset(prefix: bytes, urlsafe: bool) -> None:
    import base64

    secret = b"s3cr3t>>>???-Pa55w0rd"
    encode = base64.urlsafe_b64encode if urlsafe else base64.b64encode
    line = b"data: " + encode(prefix + secret + b'" tail')
    masked = Masker([secret.decode()]).mask(line)
    # the characters that carry the secret's bits alone (not its neighbours') are gone
    shift = len(prefix) % 3
    whole = encode(b"\0" * shift + secret)
    core = whole[-(-8 * shift // 6):8 * (shift + len(secret)) // 6]
    assert core in line and core not in masked and b"****" in masked


def test_short_values_are_not_masked_in_encoded_form() -> None:
    import base64

    text = b"payload " + base64.b64encode(b"abc" * 10)
    assert Masker(["abc"]).mask(text).startswith(b"payload ")
    assert Masker(["abc"]).mask(base64.b64encode(b"xyz")) == base64.b64encode(b"xyz")
