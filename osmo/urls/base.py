"""The contract for moving a folder to and from a URL, and the protocol that makes it atomic.

Owns :class:`Remote` (what callers use), :class:`ObjectStore` (the few object primitives a
URL scheme implements), :func:`for_url` (scheme dispatch, resolved lazily) and
:class:`Transfer`, the one implementation of the completion-marker protocol on top of any
:class:`ObjectStore`. Must not speak any wire protocol or touch a URL's storage directly: that
is each scheme module's job (:mod:`osmo.urls.local`, :mod:`osmo.urls.s3`).

The protocol (a reader never takes a partial upload for a complete one):

1. upload writes ``<prefix>/.osmo-pending.json``, then deletes any older
   ``<prefix>/.osmo-complete.json``, then writes every object, then the complete marker (each
   path with its size and sha256), then removes the pending marker;
2. download with a complete marker fetches exactly the files it lists and verifies size and
   sha256; with only a pending marker (an osmo upload running or failed) it refuses; with no
   marker at all (data osmo did not write) it fetches every object under the prefix;
3. download writes into a temporary folder beside ``dest`` and renames files into ``dest`` only
   after every one arrived and verified, so ``dest`` never holds part of a failed download.

Objects under the prefix that an upload did not list (left by older uploads) are not deleted;
a marker-guided download ignores them.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Protocol

from osmo.errors import InfrastructureError, UsageError

__all__ = ["MARKER", "PENDING", "Entry", "ObjectStore", "Remote", "Transfer", "UrlError",
           "for_url"]

MARKER = ".osmo-complete.json"
PENDING = ".osmo-pending.json"
RESERVED = frozenset({MARKER, PENDING})
FORMAT = "osmo-complete/1"
CHUNK = 1 << 20

# Lazy "module:attr" factories, imported only when a URL names the scheme.
SCHEMES: dict[str, str] = {
    "file": "osmo.urls.local:FileStore",
    "s3": "osmo.urls.s3:S3Store",
}


class UrlError(InfrastructureError):
    """A transfer to or from a URL failed (network, access, missing or corrupt object).

    The message always names the URL; it never holds a credential's secret.
    """


class Remote(Protocol):
    """A folder's worth of files at a URL, moved as a whole."""

    def upload(self, folder: Path, *, regex: str | None = None) -> list[str]:
        """Upload the files of ``folder`` (those whose relative path matches ``regex``).

        Returns:
            the relative posix paths uploaded, sorted.

        Raises:
            UsageError: ``folder`` is not a folder, ``regex`` does not compile, or a file uses
                a name the protocol reserves.
            UrlError: any write failed; no complete marker is then left at the URL.
        """
        ...

    def download(self, dest: Path, *, regex: str | None = None) -> list[str]:
        """Download into ``dest`` (created if missing) the files whose path matches ``regex``.

        Returns:
            the relative posix paths written under ``dest``, sorted.

        Raises:
            UrlError: nothing is at the URL, an upload there is incomplete, or an object is
                missing or does not match its recorded size or sha256; ``dest`` is unchanged.
        """
        ...


class ObjectStore(Protocol):
    """The object primitives one URL scheme implements; paths are relative posix paths.

    Attributes:
        url: the URL, for messages (never with secrets).
        max_object_size: the largest object one ``put`` can store, or ``None``.
    """

    url: str
    max_object_size: int | None

    def list(self) -> Iterator[tuple[str, int]]:
        """Yield ``(path, size)`` for every object under the prefix (markers included)."""
        ...

    def read(self, path: str) -> bytes | None:
        """Return a small object's bytes, or ``None`` if it does not exist."""
        ...

    def get(self, path: str, dest: Path) -> tuple[int, str]:
        """Write the object to the new file ``dest``; return its ``(size, sha256 hex)``."""
        ...

    def put(self, path: str, src: Path) -> tuple[int, str]:
        """Store the file ``src`` as one object; return the ``(size, sha256 hex)`` stored."""
        ...

    def write(self, path: str, data: bytes) -> None:
        """Store ``data`` as one object."""
        ...

    def delete(self, path: str) -> None:
        """Delete the object; a missing object is not an error."""
        ...

    def close(self) -> None:
        """Release connections; the store stays usable and reconnects when next used."""
        ...


@dataclass(frozen=True)
class Entry:
    """One file a download fetches: its path, size and (when a marker recorded it) sha256."""

    path: str
    size: int
    sha256: str | None


def for_url(url: str, credential: Mapping[str, str] | None = None) -> Remote:
    """Return the :class:`Remote` for ``url``.

    Args:
        url: ``file:///abs/path`` or ``s3://bucket/prefix``.
        credential: the scheme's keys (see each scheme module), or ``None``.

    Raises:
        UsageError: the scheme is unknown, or the URL or credential is malformed.
    """
    scheme = url.split(":", 1)[0].lower() if ":" in url else ""
    if scheme not in SCHEMES:
        supported = ", ".join(f"{s}://" for s in SCHEMES)
        raise UsageError(f"unsupported URL {url!r}: supported schemes are {supported}")
    module, attr = SCHEMES[scheme].split(":")
    factory: Callable[[str, Mapping[str, str] | None], ObjectStore]
    factory = getattr(importlib.import_module(module), attr)
    return Transfer(factory(url, credential))


def copy_hashing(read: Callable[[int], bytes], out: BinaryIO) -> tuple[int, str]:
    """Copy from ``read`` until it returns nothing into ``out``; return ``(size, sha256 hex)``."""
    h = hashlib.sha256()
    size = 0
    while chunk := read(CHUNK):
        h.update(chunk)
        out.write(chunk)
        size += len(chunk)
    return size, h.hexdigest()


def hash_file(path: Path) -> tuple[int, str]:
    """Return ``(size, sha256 hex)`` of the file at ``path``."""
    h = hashlib.sha256()
    size = 0
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK):
            h.update(chunk)
            size += len(chunk)
    return size, h.hexdigest()


def check_path(path: str, url: str) -> str:
    """Return ``path`` if it is a safe relative posix path, else raise :class:`UrlError`.

    A remote listing or marker naming ``../x`` or ``/etc/x`` must not write outside ``dest``.
    """
    parts = path.split("/")
    if not path or path.startswith("/") or any(p in ("", ".", "..") for p in parts):
        raise UrlError(f"{url}: refusing object path {path!r}: not a plain relative path")
    return path


class Transfer:
    """:class:`Remote` implemented over a :class:`ObjectStore` with the module's marker protocol.

    Attributes:
        store: the scheme's store.
    """

    def __init__(self, store: ObjectStore) -> None:
        self.store = store

    def __repr__(self) -> str:
        return f"Transfer({self.store.url!r})"

    def upload(self, folder: Path, *, regex: str | None = None) -> list[str]:
        """See :meth:`Remote.upload`."""
        files = _scan(Path(folder), _compile(regex), self.store)
        url = self.store.url
        entries = []
        with self._closing(), _wrap_os(f"uploading to {url} failed"):
            self.store.write(PENDING, b'{"format": "osmo-pending/1"}\n')
            self.store.delete(MARKER)  # before any object changes: old marker must not vouch
            for rel, src in files:
                size, sha = self.store.put(rel, src)
                entries.append({"path": rel, "size": size, "sha256": sha})
            marker = {"format": FORMAT, "files": entries}
            self.store.write(MARKER, json.dumps(marker, indent=1).encode() + b"\n")
            self.store.delete(PENDING)
        return [rel for rel, _ in files]

    def download(self, dest: Path, *, regex: str | None = None) -> list[str]:
        """See :meth:`Remote.download`."""
        pattern = _compile(regex)
        dest = Path(dest)
        with self._closing(), _wrap_os(f"downloading {self.store.url} into {dest} failed"):
            entries = [e for e in self._entries() if pattern is None or pattern.search(e.path)]
            dest.parent.mkdir(parents=True, exist_ok=True)
            tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.osmo-download-", dir=dest.parent))
            try:
                for e in entries:
                    self._fetch(e, tmp / e.path)
                _check_free(dest, entries, self.store.url)
                dest.mkdir(exist_ok=True)
                for e in entries:
                    (dest / e.path).parent.mkdir(parents=True, exist_ok=True)
                    os.replace(tmp / e.path, dest / e.path)
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
        return [e.path for e in entries]

    @contextlib.contextmanager
    def _closing(self) -> Iterator[None]:
        """Close the store's connections when the transfer ends, however it ends."""
        try:
            yield
        finally:
            self.store.close()

    def _entries(self) -> list[Entry]:
        """What a download fetches: the marker's list, else every object (module docstring)."""
        url = self.store.url
        raw = self.store.read(MARKER)
        if raw is not None:
            return _parse_marker(raw, url)
        listing = sorted(self.store.list())
        if any(path == PENDING for path, _ in listing):
            raise UrlError(f"{url}: an osmo upload there is still running or failed "
                           f"({PENDING} present, no {MARKER}); re-run the upload")
        found = [Entry(check_path(p, url), size, None) for p, size in listing if p not in RESERVED]
        if not found:
            raise UrlError(f"{url}: nothing found there (no objects under the prefix)")
        return found

    def _fetch(self, e: Entry, target: Path) -> None:
        """Fetch one entry to ``target`` and verify it against what the entry promises."""
        target.parent.mkdir(parents=True, exist_ok=True)
        size, sha = self.store.get(e.path, target)
        if size != e.size or (e.sha256 is not None and sha != e.sha256):
            raise UrlError(f"{self.store.url}: {e.path} does not match the upload's record "
                           f"(expected {e.size} bytes, sha256 {e.sha256}; got {size} bytes, "
                           f"sha256 {sha}); the data changed after upload or is corrupt")


def _compile(regex: str | None) -> re.Pattern[str] | None:
    """Compile the path filter, or raise :class:`UsageError` naming the bad pattern."""
    if regex is None:
        return None
    try:
        return re.compile(regex)
    except re.error as e:
        raise UsageError(f"invalid regex {regex!r}: {e}") from None


def _scan(folder: Path, pattern: re.Pattern[str] | None,
          store: ObjectStore) -> list[tuple[str, Path]]:
    """List ``(relative path, file)`` to upload, sorted; checks that need no writes first.

    Symlinks to files are read through (a dangling one fails when read, mid-upload, which the
    protocol makes safe); a symlink to a folder is refused rather than silently skipped.
    """
    if not folder.is_dir():
        raise UsageError(f"cannot upload {folder}: not a folder")
    out: list[tuple[str, Path]] = []
    for root, dirs, names in os.walk(folder):
        for d in dirs:
            if os.path.islink(os.path.join(root, d)):
                raise UsageError(f"cannot upload {os.path.join(root, d)}: a symlink to a folder "
                                 "(uploads follow symlinks to files only)")
        for name in names:
            src = Path(root, name)
            rel = src.relative_to(folder).as_posix()
            if pattern is None or pattern.search(rel):
                out.append((rel, src))
    out.sort()
    for rel, src in out:
        if rel in RESERVED:
            raise UsageError(f"cannot upload {src}: {rel} is a name osmo reserves at a URL")
        _check_size(rel, src, store)
    return out


def _check_size(rel: str, src: Path, store: ObjectStore) -> None:
    """Refuse, before anything is written, a file larger than one object can be."""
    try:
        size = src.stat().st_size
    except OSError:
        return  # unreadable: the upload fails on it, safely, when it gets there
    if store.max_object_size is not None and size > store.max_object_size:
        raise UrlError(f"{store.url}: {rel} is {size} bytes, over the "
                       f"{store.max_object_size}-byte limit of one object")


def _parse_marker(raw: bytes, url: str) -> list[Entry]:
    """Parse a complete marker into entries; a malformed one is a :class:`UrlError`."""
    try:
        doc = json.loads(raw)
        if doc.get("format") != FORMAT:
            raise ValueError(f"unknown format {doc.get('format')!r}")
        entries = [Entry(check_path(str(f["path"]), url), int(f["size"]), str(f["sha256"]))
                   for f in doc["files"]]
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise UrlError(f"{url}: {MARKER} is not a valid osmo marker: {e}") from None
    if len({e.path for e in entries}) != len(entries):
        raise UrlError(f"{url}: {MARKER} lists a path twice")
    return sorted(entries, key=lambda e: e.path)


def _check_free(dest: Path, entries: list[Entry], url: str) -> None:
    """Refuse before any rename when ``dest`` has a folder or file in a file's way."""
    for e in entries:
        target = dest / e.path
        if target.is_dir() and not target.is_symlink():
            raise UrlError(f"cannot download {url} into {dest}: {e.path} is a folder there")
        for parent in target.relative_to(dest).parents:
            p = dest / parent
            if p != dest and p.exists() and not p.is_dir():
                raise UrlError(f"cannot download {url} into {dest}: {parent} is a file there")


class _wrap_os:
    """Context manager: an ``OSError`` inside becomes a :class:`UrlError` with ``what``."""

    def __init__(self, what: str) -> None:
        self.what = what

    def __enter__(self) -> None:
        """Enter; nothing to set up."""
        return None

    def __exit__(self, typ: type[BaseException] | None, exc: BaseException | None,
                 tb: object) -> None:
        """Re-raise an ``OSError`` as :class:`UrlError`; let anything else through."""
        if isinstance(exc, OSError):
            name = f": {exc.filename}" if exc.filename else ""
            raise UrlError(f"{self.what}: {exc.strerror or exc}{name}") from exc
