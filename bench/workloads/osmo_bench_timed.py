"""Timed twins of the shipped task types: the same code under osmo and under Ray, with a clock.

The realistic rows (``bench/bench_sim.py``, ``bench/peers/ray_sim.py``) need the task's own
compute measured *inside* the task, identically under both systems. Each type here is the
shipped plugin type (``sim.rollout``, ``sim.eval``, ``lerobot.dataset``, ``lerobot.train``:
same name, version, params, resources and implementation) with one change: ``run`` imports
the implementation's module and the stacks it imports lazily first (``preload``: gymnasium,
mujoco, torch, lerobot's modules; so an import counts as overhead, not compute, under both
systems), then reads ``time.perf_counter`` around the shipped function and prints one line
``osmo-bench: compute SECONDS`` to stdout (the task's log under osmo).

- **osmo** runs them as custom types, ``osmo_bench_timed:rollout`` and so on, from a spec
  folder that holds a copy of this file (the worker shows that folder to the task read-only).
- **Ray** calls :func:`call` in its task, which builds the same
  :class:`~osmo.tasktypes.context.RunContext` osmo's runner builds, fills the defaults the
  same way, and returns the seconds.

Imports osmo and ``osmo_plugins`` only (the heavy stacks load when a task runs).
"""

from __future__ import annotations

import dataclasses
import importlib
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

__all__ = ["MARK", "TYPES", "TimedType", "call", "compute_of"]

MARK = "osmo-bench: compute "
"""The start of the line a timed task prints; the seconds follow."""


@dataclasses.dataclass(frozen=True)
class TimedType(PluginType):
    """A shipped :class:`PluginType` whose ``run`` also times the shipped function.

    Its ``preload`` (the shipped type's, plus what the implementation imports lazily) is
    imported before the clock: by a warm runner before the attempt, else here.
    """

    def run(self, ctx: Any) -> None:
        """Import the implementation, then run and time it; print :data:`MARK` + seconds."""
        self.timed(ctx)

    def timed(self, ctx: Any) -> float:
        """Run the shipped function with ``ctx``; return (and print) its seconds."""
        module, _, attr = self.impl.partition(":")
        fn = getattr(importlib.import_module(module), attr)
        for name in self.preload:
            importlib.import_module(name)
        t0 = time.perf_counter()
        fn(ctx)
        seconds = time.perf_counter() - t0
        print(f"{MARK}{seconds:.6f}", flush=True)
        return seconds


def _twin(shipped: PluginType, *preload: str) -> TimedType:
    fields = {f.name: getattr(shipped, f.name) for f in dataclasses.fields(shipped)}
    fields["preload"] = (*shipped.preload, *(m for m in preload if m not in shipped.preload))
    return TimedType(**fields)


_SIM = ("gymnasium", "mujoco", "osmo_plugins.sim.reach_vision", "osmo_plugins.sim.reacher")
_ACT = ("torch", "lerobot.policies.act.modeling_act", "lerobot.policies.factory")
rollout = _twin(ROLLOUT, *_SIM)
evaluate = _twin(EVAL, *_SIM, *_ACT, "osmo_plugins.lerobot.policy_io")
dataset = _twin(DATASET, "lerobot.datasets")
train = _twin(TRAIN, *_ACT, "torchvision.ops.misc", "lerobot.datasets",
              "lerobot.policies.act.configuration_act")

TYPES: dict[str, TimedType] = {"sim.rollout": rollout, "sim.eval": evaluate,
                               "lerobot.dataset": dataset, "lerobot.train": train}
"""Each timed twin by its shipped type's name; its custom-type name is ``osmo_bench_timed:ATTR``."""


def call(kind: str, params: Mapping[str, Any], inputs: Sequence[tuple[str, str]],
         output: str, task: str) -> float:
    """Run the timed twin of ``kind`` in this process, as osmo's runner would; its seconds.

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
    return typ.timed(ctx)


def compute_of(log_lines: Sequence[str]) -> float | None:
    """The seconds a timed task printed, from its log lines (None when it printed none)."""
    for line in log_lines:
        if line.startswith(MARK):
            return float(line[len(MARK):].split()[0])
    return None
