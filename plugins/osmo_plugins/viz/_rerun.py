"""MCAP → rerun ``.rrd`` conversion (imports rerun; needs the ``viz`` extra).

Episode files (:mod:`osmo_plugins.episodes`) are logged entity by entity, so a viewer shows
per-episode plots of reward, observation and action components on a ``step`` timeline and the
camera frames as images. Any other MCAP file is handed to rerun's own MCAP loader. Nothing
here opens a viewer; ``open_viewer`` does that only when asked.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from osmo_plugins.episodes import METADATA_NAME, Episode, read_episodes
from osmo_plugins.sim.envs import require

__all__ = ["episodes_to_rrd", "is_episode_file", "mcap_to_rrd", "open_viewer"]


def is_episode_file(path: Path) -> bool:
    """True when ``path`` is an MCAP of osmo episodes."""
    from osmo.record import McapFile

    with McapFile(path) as f:
        return bool(f.metadata(METADATA_NAME))


def _log_episode(rr: Any, rec: Any, prefix: str, ep: Episode) -> None:
    steps = rr.TimeColumn("step", sequence=np.arange(ep.length))
    rr.send_columns(f"{prefix}/reward", indexes=[steps],
                    columns=rr.Scalars.columns(scalars=ep.rewards.astype(np.float64)),
                    recording=rec)
    for name, values in (("observation", ep.observations), ("action", ep.actions)):
        for j in range(values.shape[1]):
            rr.send_columns(f"{prefix}/{name}/{j}", indexes=[steps],
                            columns=rr.Scalars.columns(scalars=values[:, j].astype(np.float64)),
                            recording=rec)
    rec.log(f"{prefix}/summary", rr.TextDocument(
        f"seed {ep.seed}: return {ep.total_reward:.2f} over {ep.length} steps, "
        f"terminated={ep.terminated}"), static=True)
    if ep.frames is not None:
        for t, frame in enumerate(ep.frames):
            rec.set_time("step", sequence=t)
            rec.log(f"{prefix}/camera", rr.Image(frame))


def episodes_to_rrd(files: Sequence[tuple[str, Path]], out: Path,
                    app_id: str = "osmo") -> Path:
    """Write the episodes of ``(label, mcap)`` pairs to one ``.rrd`` at ``out``."""
    rr = require("rerun", "viz")
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(app_id)
    rec.save(str(out))
    for label, path in files:
        for ep in read_episodes(path):
            _log_episode(rr, rec, f"{label}/episode_{ep.index:03d}", ep)
    rec.flush()
    rec.disconnect()
    return out


def mcap_to_rrd(path: Path, out: Path, app_id: str = "osmo") -> Path:
    """One MCAP file → ``.rrd``: structured for episode files, rerun's loader for others."""
    if is_episode_file(path):
        return episodes_to_rrd([(path.stem, path)], out, app_id)
    rr = require("rerun", "viz")
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(app_id)
    rec.save(str(out))
    rec.log_file_from_path(path)
    rec.flush()
    rec.disconnect()
    return out


def open_viewer(rrd: Path) -> bool:
    """Start the rerun viewer on ``rrd`` in the background.

    Returns False when there is no viewer binary or no display.
    """
    import os

    exe = shutil.which("rerun")
    if exe is None or not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return False
    subprocess.Popen([exe, str(rrd)], start_new_session=True,  # noqa: S603
                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return True
