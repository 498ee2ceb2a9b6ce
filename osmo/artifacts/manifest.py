r"""Manifests: the frozen list of (path, digest, size) an attempt's outputs consist of.

Owns the :class:`Entry` and :class:`Manifest` records, their canonical JSON form and the
digest string format (``"sha256:<64 lowercase hex>"``). It validates what a manifest may
contain (relative posix paths that stay inside the output folder, well-formed digests), so
that a manifest read from anywhere is safe to materialize.

File names are bytes. The one encoding rule, everywhere osmo keeps or sends a name:

- **In memory** a name is the ``str`` that :func:`os.fsdecode` makes of its bytes: UTF-8,
  where every byte that is not part of valid UTF-8 becomes one lone surrogate
  ``U+DC80..U+DCFF`` (PEP 383, ``surrogateescape``). ``os.fsencode(name)`` gives back the
  exact bytes, so ``open``, ``os.link`` and friends write the same name on every host. A
  path holding any other surrogate is rejected (it names no bytes).
- **In JSON** (manifests, lineage, the API, worker traffic, MCAP run records) names are
  written with ``ensure_ascii``: a valid UTF-8 name reads as itself in any JSON reader, and a
  byte such as ``0xE9`` that is not UTF-8 appears as the escape ``\udce9``, which Python's
  ``json`` reads back into the same ``str``. Manifests written before this rule use the same
  form (they simply never held such a name), so every old manifest reads unchanged.
- **In SQLite** (``osmo.store``) a name that is valid UTF-8 is ``TEXT``; any other name is a
  ``BLOB`` of its raw bytes (``CAST(path AS BLOB)`` gives the bytes of either).
- **In messages** a name is quoted with ``repr`` (so it is one line of ASCII-safe text),
  and whoever prints a name for a terminal escapes it (the CLI: ``osmo.cli.render.safe``).

Must not touch the filesystem or the blob store; that is :mod:`osmo.artifacts.store`'s job.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import dataclass
from functools import cached_property
from typing import Any

from osmo.errors import InfrastructureError, UsageError

__all__ = ["MANIFEST_VERSION", "Entry", "Manifest", "check_digest"]

MANIFEST_VERSION = 1
_DIGEST = re.compile(r"sha256:[0-9a-f]{64}")


def check_digest(digest: str) -> str:
    """Return the hex part of ``digest`` after checking its form.

    Args:
        digest: a digest string such as ``"sha256:9f86d0..."``.

    Returns:
        The 64 lowercase hex characters after ``sha256:``.

    Raises:
        UsageError: ``digest`` is not ``"sha256:"`` followed by 64 lowercase hex characters.
    """
    if not isinstance(digest, str) or not _DIGEST.fullmatch(digest):
        raise UsageError(f"invalid artifact digest {digest!r}: expected 'sha256:' followed by "
                         "64 lowercase hex characters")
    return digest[7:]


def _check_path(path: str) -> None:
    """Reject a path that cannot be one of a manifest's files.

    Absolute, empty, non-canonical, climbing out of the folder, or naming no bytes (a surrogate that
    ``surrogateescape`` never makes).
    """
    parts = path.split("/") if isinstance(path, str) else [""]
    if (not isinstance(path, str) or not path or path.startswith("/") or "\\" in path
            or "\0" in path or any(p in ("", ".", "..") for p in parts)):
        raise UsageError(f"invalid artifact path {path!r}: expected a relative posix path "
                         "inside the output folder (no '', '.', '..' parts, no backslashes)")
    try:
        os.fsencode(path)
    except UnicodeEncodeError:
        raise UsageError(f"invalid artifact path {path!r}: it holds a surrogate that stands "
                         "for no byte") from None


@dataclass(frozen=True)
class Entry:
    """One output file.

    Attributes:
        path: the file's path relative to the output folder, posix separators.
        digest: ``"sha256:<hex>"`` of the file's content.
        size: the content's length in bytes.

    Raises:
        UsageError: on construction, when a field is malformed.
    """

    path: str
    digest: str
    size: int

    def __post_init__(self) -> None:
        _check_path(self.path)
        check_digest(self.digest)
        if not isinstance(self.size, int) or isinstance(self.size, bool) or self.size < 0:
            raise UsageError(f"invalid size {self.size!r} for artifact {self.path!r}")


@dataclass(frozen=True)
class Manifest:
    """The outputs of one attempt: entries sorted by path, each path at most once.

    Entries are sorted on construction, so two manifests of the same files compare equal and
    have the same :attr:`digest` whatever order they were listed in.

    Attributes:
        entries: the files, sorted by ``path``.

    Raises:
        UsageError: on construction, when a path repeats or is both a file and a folder.
    """

    entries: tuple[Entry, ...]

    def __post_init__(self) -> None:
        entries = tuple(sorted(self.entries, key=lambda e: e.path))
        object.__setattr__(self, "entries", entries)  # normalise the frozen field once
        files: set[str] = set()
        folders: set[str] = set()
        for e in entries:
            if e.path in files or e.path in folders:
                raise UsageError(f"artifact path {e.path!r} appears twice in a manifest "
                                 "(or as both a file and a folder)")
            files.add(e.path)
            parts = e.path.split("/")
            folders.update("/".join(parts[:i]) for i in range(1, len(parts)))
        clash = files & folders
        if clash:
            raise UsageError(f"artifact path {min(clash)!r} is both a file and a folder "
                             "in a manifest")

    def to_json(self) -> str:
        """Return the canonical JSON text (sorted keys, no spaces, ASCII only).

        The text is stable: the same entries always give the same bytes, which is what
        :attr:`digest` hashes.
        """
        doc = {"version": MANIFEST_VERSION,
               "entries": [{"path": e.path, "digest": e.digest, "size": e.size}
                           for e in self.entries]}
        return json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=True)

    @classmethod
    def from_json(cls, text: str) -> Manifest:
        """Parse the text :meth:`to_json` wrote.

        Args:
            text: JSON as written by :meth:`to_json` (whitespace and key order may differ).

        Returns:
            The manifest.

        Raises:
            InfrastructureError: the text is not a manifest of a known version.
        """
        try:
            doc: Any = json.loads(text)
            if not isinstance(doc, dict) or doc.get("version") != MANIFEST_VERSION:
                raise ValueError(f"expected an object with version {MANIFEST_VERSION}")
            rows = doc["entries"]
            if not isinstance(rows, list):
                raise ValueError("'entries' must be a list")
            return cls(tuple(Entry(r["path"], r["digest"], r["size"]) for r in rows))
        except (ValueError, KeyError, TypeError, UsageError) as exc:
            raise InfrastructureError(f"invalid artifact manifest: {exc}") from exc

    @cached_property
    def digest(self) -> str:
        """``"sha256:<hex>"`` of :meth:`to_json`'s UTF-8 bytes; equal manifests, equal digests."""
        return "sha256:" + hashlib.sha256(self.to_json().encode("ascii")).hexdigest()

    @property
    def size(self) -> int:
        """Total bytes of all entries."""
        return sum(e.size for e in self.entries)

    def get(self, path: str) -> Entry | None:
        """Return the entry at ``path``, or ``None`` when the manifest has no such file."""
        return next((e for e in self.entries if e.path == path), None)
