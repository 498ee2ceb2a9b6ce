"""The task-type object every built-in plugin exports, with its implementation loaded lazily.

A :class:`PluginType` carries the declared attributes of ``osmo.tasktypes.TaskType`` and the
``"module:function"`` that does the work. ``run`` imports that module only when the task runs,
so ``osmo plugins list`` can import every entry point without numpy, gymnasium, torch or
rerun installed, and report the missing extra instead of an import error.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Self

from osmo.tasktypes.api import Param, TaskContext
from osmo.tasktypes.reports import Report

__all__ = ["ACT_PRELOAD", "HF_ENV", "SIM_PRELOAD", "Committing", "PluginType",
           "find_folder_with", "find_folders_with", "offline"]

HF_ENV: Mapping[str, str] = {"HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1",
                             "HF_DATASETS_DISABLE_PROGRESS_BARS": "1"}
"""Hugging Face's offline switches and no progress bars of ``datasets`` (:func:`offline`).
Its libraries read them when imported, so a type that preloads ``lerobot`` in a warm runner
sets them there too (``preload_env``). Without the last, writing a LeRobotDataset put a
progress-bar line per saved episode into the task's log (400 of the demo dataset task's 810
lines); osmo reports a task's progress itself (``ctx.progress``)."""

MUJOCO_V5 = ("ant", "half_cheetah", "hopper", "humanoid", "humanoidstandup",
             "inverted_double_pendulum", "inverted_pendulum", "pusher", "reacher", "swimmer",
             "walker2d")
"""Gymnasium's MuJoCo v5 envs (``gymnasium.envs.mujoco.NAME_v5``: ``gym.make`` imports one)."""

SIM_PRELOAD = ("numpy", "gymnasium", "mujoco", "gymnasium.envs.mujoco",
               *(f"gymnasium.envs.mujoco.{name}_v5" for name in MUJOCO_V5),
               "osmo_plugins.sim.reach_vision", "osmo_plugins.sim.reacher",
               "foxglove", "foxglove.mcap", "foxglove.channels", "foxglove.messages",
               "osmo_plugins.foxglove_io")
"""What every simulation run imports: the stack, its MuJoCo envs (each run makes one, which
imports its module), osmo's own envs and the MCAP writer (the Foxglove SDK: every run
records its episodes; about 10 ms to import, in each fork otherwise)."""

ACT_PRELOAD = ("torch", "lerobot.policies.act.configuration_act",
               "lerobot.policies.act.modeling_act", "lerobot.policies.factory")
"""What loading an ACT policy imports (torch and LeRobot's ACT: seconds each).

Not preloaded by the LeRobot types themselves: these modules import Hugging Face's
``datasets``, which fixes its cache folders from ``HOME`` when imported, so a runner would
hand every attempt the runner's folders (not writable in an attempt's sandbox), and training
and dataset writing use that cache. Evaluation loads a policy and never touches it."""


class Committing:
    """A writer used as a context manager.

    ``close()`` (commit) after a clean block, ``abort()`` (discard) after an exception.
    Subclasses define both.
    """

    def __enter__(self) -> Self:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if kind is None:
            self.close()
        else:
            self.abort()

    def close(self) -> None:
        """Finish and keep what was written."""
        raise NotImplementedError

    def abort(self) -> None:
        """Discard what was written."""
        raise NotImplementedError


@dataclass(frozen=True)
class PluginType:
    """A task type whose ``run`` calls ``impl`` (``"package.module:function"``).

    ``report``: what ``osmo eval report`` shows of its outputs (``osmo.tasktypes.reports``).
    ``preload``: modules a warm runner imports besides ``impl`` (:meth:`warm`), those every
    run needs; ``preload_env``: variables set while it imports them (only), so that a module
    which reads the environment at import decides nothing for the runs (MuJoCo's GL backend:
    ``MUJOCO_GL=disable`` leaves it to each run's first renderer).
    """

    name: str
    version: str
    description: str
    impl: str
    extra: str | None
    params: Mapping[str, Param] = field(default_factory=dict)
    resources: Mapping[str, Any] = field(default_factory=dict)
    report: Report | None = None
    preload: tuple[str, ...] = ()
    preload_env: Mapping[str, str] = field(default_factory=dict)

    def run(self, ctx: TaskContext) -> None:
        """Import the implementation and run it with ``ctx``."""
        module, _, attr = self.impl.partition(":")
        getattr(importlib.import_module(module), attr)(ctx)

    def warm(self) -> None:
        """Import what every run needs, once, in a warm runner (``osmo.runtime.process.warm``).

        A module that is not installed is left to the run, which then says which extra.
        """
        saved = {name: os.environ.get(name) for name in self.preload_env}
        os.environ.update(self.preload_env)
        try:
            for module in (*self.preload, self.impl.partition(":")[0]):
                try:
                    importlib.import_module(module)
                except ImportError:
                    continue
        finally:
            for name, value in saved.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value


def find_folder_with(folders: Any, marker: str) -> Any:
    """The first folder holding a file ``marker`` (:func:`find_folders_with`), or None."""
    return next(_folders_with(folders, marker), None)


def find_folders_with(folders: Any, marker: str) -> list[Any]:
    """Every folder holding a file ``marker``.

    Each input folder is searched recursively, in order (the hits of one input sorted).
    """
    return list(_folders_with(folders, marker))


def _folders_with(folders: Any, marker: str) -> Iterator[Any]:
    from pathlib import Path

    for folder in folders:
        for hit in sorted(Path(folder).rglob(marker)):
            yield hit.parent


def offline() -> None:
    """Make Hugging Face libraries work from local files only, with no progress bars.

    Plugins never download weights or datasets at run time (set before ``lerobot`` or
    ``huggingface_hub`` is imported). A task's own environment wins (``HF_ENV``).
    """
    for name, value in HF_ENV.items():
        os.environ.setdefault(name, value)
