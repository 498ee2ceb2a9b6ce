"""The work of ``viz.rerun`` (params in :mod:`osmo_plugins.viz.rerun_view`)."""

from __future__ import annotations

from pathlib import Path

from osmo.tasktypes.api import TaskContext
from osmo_plugins.viz._rerun import episodes_to_rrd, is_episode_file, mcap_to_rrd

__all__ = ["run"]


def run(ctx: TaskContext) -> None:
    """Convert every matching MCAP of the inputs."""
    files = [f for folder in ctx.inputs for f in sorted(Path(folder).rglob(ctx.params["pattern"]))
             if f.is_file() and not f.name.startswith(".")]
    if not files:
        raise ValueError(f"no files matching {ctx.params['pattern']!r} in the inputs")
    out = Path(ctx.output)
    if ctx.params["combine"]:
        episode_files = [(f.stem, f) for f in files if is_episode_file(f)]
        episodes_to_rrd(episode_files, out / "combined.rrd", app_id=ctx.workflow_id)
        ctx.log.info("wrote combined.rrd from %d episode file(s)", len(episode_files))
        return
    for n, f in enumerate(files):
        ctx.check_cancelled()
        target = out / f"{f.stem}.rrd"
        if target.exists():  # same stem from two inputs: keep both
            target = out / f"{f.stem}-{n}.rrd"
        mcap_to_rrd(f, target, app_id=ctx.workflow_id)
        ctx.progress(n + 1, len(files), target.name)
        ctx.log.info("%s → %s", f.name, target.name)
