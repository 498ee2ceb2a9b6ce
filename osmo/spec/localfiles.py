"""Which files a spec's ``files: localpath:`` may read: its own folder tree, never osmo's home.

A ``localpath`` is relative to the spec file's folder. Its contents are inlined into the
submitted spec, which every user of the server may print (``osmo spec``), so the path must
resolve (symlinks followed) inside that folder tree, or inside a folder the submitter widened
it to (``--allow-localpath DIR``, :attr:`LocalFiles.allowed`), and never inside an osmo home
(:attr:`LocalFiles.hidden`: the ``OSMO_HOME`` in effect and any the caller adds), even where an
allowed folder covers it: that home holds the admin token and the state store.

The rule is checked on the resolved path before anything is opened, and again on the file
actually opened (its ``/proc/self/fd`` link), so a symlink swapped in between gets no further.
A spec given as data (``spec_from_dict``: what a server or worker receives) reads no local file
at all (:meth:`LocalFiles.none`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from osmo.config import home_path
from osmo.spec.files import FileRefused, read_regular_file

__all__ = ["LocalFiles", "LocalPathRefused"]


class LocalPathRefused(FileRefused):
    """A ``localpath`` the rule of the module docstring refuses; the message says why."""


@dataclass(frozen=True)
class LocalFiles:
    """Where a spec's ``localpath`` files may be read from (see the module docstring).

    Attributes:
        base: the spec's folder, resolved (None: this spec reads no local file).
        allowed: more folders, resolved, whose trees may be read (``--allow-localpath``).
        hidden: folders, resolved, never read (osmo homes).
    """

    base: Path | None
    allowed: tuple[Path, ...] = ()
    hidden: tuple[Path, ...] = ()

    @classmethod
    def under(cls, base: str | os.PathLike[str], *,
              allow: Sequence[str | os.PathLike[str]] = (),
              deny: Sequence[str | os.PathLike[str]] = ()) -> LocalFiles:
        """The files of ``base``'s and ``allow``'s trees, but none in osmo's home or ``deny``."""
        return cls(Path(base).resolve(), tuple(Path(p).resolve() for p in allow),
                   (home_path(), *(Path(p).resolve() for p in deny)))

    @classmethod
    def none(cls) -> LocalFiles:
        """No local file at all (a spec given as data)."""
        return cls(None)

    def read(self, name: str, *, limit: int) -> bytes:
        """The bytes of ``localpath`` ``name`` (regular files only, at most ``limit``).

        Raises:
            LocalPathRefused: the path breaks the rule (nothing was read).
            FileRefused: it is not a regular file, or is larger than ``limit``.
            OSError: it cannot be read (missing, no permission...).
        """
        if self.base is None:
            raise LocalPathRefused("is not read: only a spec file's own folder holds "
                                   "localpath files (`osmo submit FILE` inlines them)")
        path = self.base / name
        self._check(os.path.realpath(path))
        return read_regular_file(path, limit=limit, check=self._check)

    def _check(self, real: str) -> None:
        """Refuse ``real`` (a resolved path) unless the rule allows it."""
        target = Path(real)
        for home in self.hidden:
            if _within(target, home):
                raise LocalPathRefused(f"resolves to {real}, inside osmo's home {home}, which "
                                       "a spec may never read")
        if not any(_within(target, root) for root in (self.base, *self.allowed) if root):
            raise LocalPathRefused(
                f"resolves to {real}, outside the spec's folder {self.base}; a localpath must "
                "stay inside the spec's folder tree (widen it with --allow-localpath DIR)")


def _within(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents
