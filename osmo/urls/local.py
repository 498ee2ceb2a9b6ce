"""``file://`` URLs: a folder on this host (or a shared mount) as the object store.

Owns parsing ``file:///abs/path`` and the :class:`~osmo.urls.base.ObjectStore` primitives on a
folder: every object is written to a temporary name beside its final one and renamed, so a
reader never sees a half-written file under its final name. Must not implement the marker
protocol (that is :class:`osmo.urls.base.Transfer`) nor fsync: a write survives a crash of the
process, not a power loss.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import BinaryIO, TypeVar
from urllib.parse import unquote, urlsplit

from osmo.errors import UsageError
from osmo.urls.base import UrlError, check_path, copy_hashing

__all__ = ["FileStore"]

_T = TypeVar("_T")
_TMP = ".osmo-tmp-"  # infix of in-flight temporary names; never listed


def parse_file_url(url: str) -> Path:
    """Return the absolute folder a ``file:///abs/path`` URL names.

    Raises:
        UsageError: the URL has a host (``file://host/p``) or a relative path.
    """
    parts = urlsplit(url)
    if parts.scheme.lower() != "file":
        raise UsageError(f"not a file:// URL: {url!r}")
    if parts.netloc not in ("", "localhost"):
        raise UsageError(f"file URL {url!r} names host {parts.netloc!r}; write an absolute "
                         f"local path with three slashes, e.g. file:///data/out")
    path = unquote(parts.path)
    if not path.startswith("/") or parts.query or parts.fragment:
        raise UsageError(f"file URL {url!r} must be an absolute path without query or "
                         f"fragment, e.g. file:///data/out")
    return Path(os.path.normpath(path))


class FileStore:
    """A folder as an object store; object ``a/b.txt`` is the file ``<root>/a/b.txt``.

    Attributes:
        url: the URL as given.
        root: the folder it names.
        max_object_size: ``None`` (no limit beyond the file system's).
    """

    max_object_size: int | None = None

    def __init__(self, url: str, credential: Mapping[str, str] | None = None) -> None:
        """Parse ``url``; ``file://`` takes no credential.

        Raises:
            UsageError: the URL is malformed, or a non-empty credential was given.
        """
        if credential:
            raise UsageError(f"{url}: file:// URLs take no credential (got keys "
                             f"{sorted(credential)}); remove it")
        self.url = url
        self.root = parse_file_url(url)

    def __repr__(self) -> str:
        return f"FileStore({self.url!r})"

    def _path(self, path: str) -> Path:
        """The file of a relative path (checked: no ``..``, no leading ``/``)."""
        return self.root / check_path(path, self.url)

    def list(self) -> Iterator[tuple[str, int]]:
        """Yield ``(path, size)`` of every file under the root (none if it does not exist)."""
        if self.root.exists() and not self.root.is_dir():
            raise UrlError(f"{self.url}: {self.root} is a file, not a folder")
        for root, _dirs, names in os.walk(self.root):
            for name in names:
                if _TMP in name:
                    continue
                full = Path(root, name)
                yield full.relative_to(self.root).as_posix(), full.stat().st_size

    def read(self, path: str) -> bytes | None:
        """Return the file's bytes, or ``None`` if it does not exist."""
        try:
            return self._path(path).read_bytes()
        except (FileNotFoundError, NotADirectoryError):
            return None

    def get(self, path: str, dest: Path) -> tuple[int, str]:
        """Copy the object to the new file ``dest``; return its ``(size, sha256 hex)``.

        Raises:
            UrlError: the object does not exist.
        """
        try:
            src = open(self._path(path), "rb")
        except (FileNotFoundError, NotADirectoryError):
            raise UrlError(f"{self.url}: object {path} not found") from None
        with src, open(dest, "xb") as out:
            return copy_hashing(src.read, out)

    def put(self, path: str, src: Path) -> tuple[int, str]:
        """Copy ``src`` to the object (temporary name, then rename); return what was copied."""
        with open(src, "rb") as f:
            return self._atomic(path, lambda out: copy_hashing(f.read, out))

    def write(self, path: str, data: bytes) -> None:
        """Write ``data`` to the object (temporary name, then rename)."""
        self._atomic(path, lambda out: (out.write(data), "")[1])

    def delete(self, path: str) -> None:
        """Remove the object's file if it exists."""
        self._path(path).unlink(missing_ok=True)

    def close(self) -> None:
        """Nothing to release: a folder holds no connection."""

    def _atomic(self, path: str, fill: Callable[[BinaryIO], _T]) -> _T:
        """Create the object by ``fill`` into a temporary file renamed over the final name."""
        final = self._path(path)
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = final.with_name(f".{final.name}{_TMP}{secrets.token_hex(4)}")
        try:
            with open(tmp, "xb") as out:
                result = fill(out)
            os.replace(tmp, final)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return result
