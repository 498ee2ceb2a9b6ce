"""Masking of secret values in log lines.

A :class:`Masker` replaces every occurrence of any of its secret values by ``****``. It works
on bytes, before decoding, so a value is found whatever its characters are, and on complete
lines (the log writer assembles them), so a value split across two pipe reads is still
found. Overlapping occurrences of different values are merged and masked as one.

A value that spans several lines (a PEM key) can never appear whole in one line: each of its
lines is masked on its own as well. Very short values are masked too, but a secret of one or
two characters masks every occurrence of those characters in the log, secret or not; such a
secret is weak anyway.

A value is masked in its base64 and base64url forms too, as CI systems do (``echo $TOKEN |
base64`` must not print it in the clear): inside a longer encoded text a value can start at
any of three offsets, each encoding it differently, so the characters that depend on the
value alone are masked for each offset, in both alphabets (the one or two characters at each
end, which also carry the neighbouring bytes, stay). Values shorter than 4 bytes are not
masked in encoded form: their encodings are a few characters long and would mask random
base64 text.

This module only transforms text; it does not know where secrets come from.
"""

from __future__ import annotations

import base64
from collections.abc import Iterable

__all__ = ["MASK", "Masker", "encoded_forms"]

MASK = b"****"
_MIN_ENCODED = 4  # bytes: shorter values are not masked in their encoded forms
_URLSAFE = bytes.maketrans(b"+/", b"-_")


def encoded_forms(value: bytes) -> set[bytes]:
    """How ``value`` can show in base64 and base64url text (see the module docstring)."""
    if len(value) < _MIN_ENCODED:
        return set()
    forms: set[bytes] = set()
    whole = base64.b64encode(value)
    for form in (whole, whole.rstrip(b"=")):
        forms |= {form, form.translate(_URLSAFE)}
    for shift in range(3):  # the value's offset in the encoded text, modulo 3
        encoded = base64.b64encode(b"\0" * shift + value)
        core = encoded[-(-8 * shift // 6):8 * (shift + len(value)) // 6]
        forms |= {core, core.translate(_URLSAFE)}
    return forms


class Masker:
    """Replaces the given secret values by ``****`` (empty values are ignored).

    Args:
        values: the secret values (text).
    """

    def __init__(self, values: Iterable[str] = ()) -> None:
        found: set[bytes] = set()
        for value in values:
            found.add(value.encode())
            found.update(line.encode() for line in value.splitlines())
        found.discard(b"")
        for plain in list(found):
            found |= encoded_forms(plain)
        # Longest first: the common case is a value that is not a part of another one.
        self._values = tuple(sorted(found, key=len, reverse=True))
        self.hold = max((len(v) for v in self._values), default=1) - 1
        """Bytes to hold back at the end of an unfinished line: a value may start there."""

    def __bool__(self) -> bool:
        return bool(self._values)

    def mask(self, data: bytes) -> bytes:
        """``data`` with every occurrence of a secret value replaced by ``****``."""
        if not self._values:
            return data
        spans = sorted(self._spans(data))
        if not spans:
            return data
        out, pos = [], 0
        for start, end in _merged(spans):
            out += [data[pos:start], MASK]
            pos = end
        out.append(data[pos:])
        return b"".join(out)

    def mask_text(self, text: str) -> str:
        """:meth:`mask` for text."""
        if not self._values:
            return text
        return self.mask(text.encode("utf-8", "surrogateescape")).decode("utf-8", "replace")

    def _spans(self, data: bytes) -> Iterable[tuple[int, int]]:
        for value in self._values:
            start = data.find(value)
            while start >= 0:
                yield start, start + len(value)
                start = data.find(value, start + 1)  # overlapping occurrences too


def _merged(spans: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """Sorted spans with overlapping or touching ones joined."""
    merged = [spans[0]]
    for start, end in spans[1:]:
        last_start, last_end = merged[-1]
        if start <= last_end:
            merged[-1] = (last_start, max(last_end, end))
        else:
            merged.append((start, end))
    return merged
