"""The rerun viewer ``osmo view`` uses (the ``osmo.viewers`` entry point ``rerun``).

Importing this module needs nothing beyond osmo; rerun (the ``viz`` extra) is imported when
a file is converted.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["VIEWER", "RerunViewer"]


class RerunViewer:
    """MCAP (episode files structured, any other through rerun's loader) → rerun ``.rrd``."""

    name = "rerun"
    suffix = ".rrd"

    def convert(self, source: Path, out: Path) -> Path:
        """Write ``source`` as the rerun recording ``out``."""
        from osmo_plugins.viz._rerun import mcap_to_rrd

        return Path(mcap_to_rrd(source, out))

    def open(self, path: Path) -> bool:
        """Start the rerun viewer on ``path``; False without a viewer binary or display."""
        from osmo_plugins.viz._rerun import open_viewer

        return open_viewer(path)


VIEWER = RerunViewer()
