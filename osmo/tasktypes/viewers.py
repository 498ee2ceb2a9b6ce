"""Viewers plugins contribute: ``osmo view`` turns a recording into a viewer's file.

A plugin registers a viewer under the ``osmo.viewers`` entry-point group
(``rerun = "osmo_plugins.viz.viewer:VIEWER [viz]"``). The object has the :class:`Viewer`
shape; the module it lives in must import without the viewer's own dependencies (import them
inside ``convert``/``open``, raising :class:`osmo.errors.MissingExtra` when they are absent),
so ``osmo view --help`` works everywhere. The core never imports a plugin's modules itself.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol, runtime_checkable

from osmo.errors import UsageError
from osmo.tasktypes.registry import entry_points, extra_of, import_failure

__all__ = ["VIEWER_GROUP", "Viewer", "find_viewer", "viewer_names"]

VIEWER_GROUP = "osmo.viewers"
"""The entry-point group plugins register their viewers in."""


@runtime_checkable
class Viewer(Protocol):
    """What a viewer plugin provides.

    Attributes:
        name: the name ``osmo view --viewer`` takes.
        suffix: the suffix of the files ``convert`` writes (``.rrd``); such a file is shown
            as it is.
    """

    name: str
    suffix: str

    def convert(self, source: Path, out: Path) -> Path:
        """Write ``source`` (an MCAP file) as the viewer's file ``out``; returns ``out``."""
        ...

    def open(self, path: Path) -> bool:
        """Open the viewer on ``path`` in the background; False when it cannot here."""
        ...


def viewer_names() -> list[str]:
    """The installed viewers, by name."""
    return sorted(entry_points(VIEWER_GROUP))


def find_viewer(name: str | None = None) -> Viewer:
    """The viewer called ``name`` (None: the only one installed, or ``rerun``).

    Raises:
        UsageError: none is installed, ``name`` is unknown, or it does not load (with the pip
            extra to install when a dependency is missing).
    """
    eps = entry_points(VIEWER_GROUP)
    if not eps:
        raise UsageError('no viewer is installed: pip install "osmo[viz]"')
    if name is None:
        name = next(iter(eps)) if len(eps) == 1 else "rerun"
    ep = eps.get(name)
    if ep is None:
        raise UsageError(f"no viewer '{name}'; installed: {', '.join(sorted(eps))}")
    try:
        viewer = ep.load()
    except Exception as exc:  # noqa: BLE001 - a plugin's import failure is the user's message
        raise UsageError(import_failure(f"viewer '{name}'", ep.module, exc, extra_of(ep))) \
            from exc
    if not isinstance(viewer, Viewer) or not isinstance(getattr(viewer, "suffix", None), str):
        raise UsageError(f"viewer '{name}' ({ep.value}) does not have the shape of a viewer "
                         "(name, suffix, convert(source, out), open(path))")
    return viewer
