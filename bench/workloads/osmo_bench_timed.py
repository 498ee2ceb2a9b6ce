"""The shipped task types, timed inside the task the same way under osmo and under Ray.

The realistic rows (``bench/bench_sim.py``, ``bench/peers/ray_sim.py``) need the task's own
compute measured *inside* the task, identically under both systems: the shipped type's
``warm()`` first (its ``preload`` and implementation module, so an import counts as overhead,
not compute, under both systems), then ``time.perf_counter`` around its ``run``.

- **osmo** runs the shipped types themselves, with ``OSMO_TASK_TIMING=1`` in each task's
  environment: osmo's runner (``osmo.tasktypes.runner``) then does exactly that and prints
  ``osmo: compute SECONDS`` to the task's log; a warm runner has imported them already.
- **Ray** calls :func:`call` in its task, which builds the same
  :class:`~osmo.tasktypes.context.RunContext` osmo's runner builds, fills the defaults the
  same way, and returns the seconds.

Imports osmo and ``osmo_plugins`` only (the heavy stacks load when a task runs).
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from osmo_plugins._base import PluginType
from osmo_plugins.lerobot.dataset import DATASET
from osmo_plugins.lerobot.train import TRAIN
from osmo_plugins.sim.eval import EVAL
from osmo_plugins.sim.rollout import ROLLOUT

from osmo.params import fill_defaults
from osmo.tasktypes.context import RunContext
from osmo.tasktypes.runner import TIMING, TIMING_MARK

__all__ = ["TIMING", "TYPES", "call", "compute_of"]

TYPES: dict[str, PluginType] = {t.name: t for t in (ROLLOUT, EVAL, DATASET, TRAIN)}
"""The shipped types the workloads run, by name."""


def call(kind: str, params: Mapping[str, Any], inputs: Sequence[tuple[str, str]],
         output: str, task: str) -> float:
    """Run the shipped type ``kind`` in this process, timed as osmo's runner times it.

    ``inputs``: (upstream task name, its output folder) pairs, in order. ``output`` is made
    if missing; the work folder is beside it.
    """
    typ = TYPES[kind]
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    work = out.parent / f"{out.name}.work"
    work.mkdir(exist_ok=True)
    ctx = RunContext(params=fill_defaults(typ.params, dict(params)),
                     inputs=[Path(p) for _, p in inputs],
                     input_named={name: Path(p) for name, p in inputs}, output=out,
                     workdir=work, workflow_id="bench", task=task, attempt_id=task,
                     plugin=f"{typ.name}@{typ.version}")
    typ.warm()
    start = time.perf_counter()
    typ.run(ctx)
    return time.perf_counter() - start


def compute_of(log_lines: Sequence[str]) -> float | None:
    """The seconds osmo's runner printed for a timed task, from its log lines (None if none)."""
    for line in log_lines:
        if line.startswith(TIMING_MARK):
            return float(line[len(TIMING_MARK):].split()[0])
    return None
