"""Runtimes: how an attempt runs on a node, from its launch to its clean-up.

One folder per runtime family, one module per runtime:

- ``api`` — the contract every runtime keeps (:class:`Runtime`: one method per concern,
  in the order the pool calls them) and its types (:class:`Launch`, :class:`Paths`, ...);
  ``osmo.testing.check_runtime`` checks a runtime against it.
- ``choose`` — the one chooser: which runtimes a node has, and which runs each attempt.
- ``process/`` — host processes: ``runtime`` (plain), ``sandboxed`` (in bubblewrap),
  and what they share (``groups``: process groups; ``sandbox``; ``netns``; ``proctable``;
  ``ports``).
- ``container/`` — the task's image: ``runtime`` (the runtime), ``engine`` (the only module
  that runs podman or docker), ``run`` (argv), ``runs`` (a run's life), ``pull``,
  ``images``, ``layout`` (OSMO's data layout), ``groups`` (group networks).
- ``kubernetes/`` — the task's image as a pod of a cluster (``osmo worker --runtime
  kubernetes``): ``runtime``, ``manifest``, ``status`` (the one status table), ``follow``
  (a pod's life), ``groups`` (gangs), ``kube`` (the only module importing the client),
  ``config``, ``capacity``, ``exec_relay``.
- ``background`` — a runtime's own background calls (removals), waited for at close.

A Slurm job is one more folder here, one more runtime for the chooser.
Runtimes know nothing of the scheduler's state or of logs; the worker pool drives them.
"""

from osmo.runtime.api import (
    HOST_PATHS,
    Adopting,
    Attempt,
    ConnectError,
    Connector,
    ExecCommand,
    Launch,
    Paths,
    PrepareError,
    ProcessHandle,
    Runtime,
    StartError,
)
from osmo.runtime.process.groups import ProcessGroups, exit_code_of
from osmo.runtime.process.proctable import kill_stale, process_start_time

__all__ = [
    "HOST_PATHS",
    "Adopting",
    "Attempt",
    "ConnectError",
    "Connector",
    "ExecCommand",
    "Launch",
    "Paths",
    "PrepareError",
    "ProcessGroups",
    "ProcessHandle",
    "Runtime",
    "StartError",
    "exit_code_of",
    "kill_stale",
    "process_start_time",
]
