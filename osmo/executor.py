"""The executor port: what runs attempts for the server's engine.

The local pool (``osmo.worker.pool.LocalPool``: the attempts of the server's machine) and
the remote-worker hub (``osmo.server.workers.WorkerHub``: workers reached over zenoh, each
running its own local pool) implement it. How a pool runs one attempt — a host process,
sandboxed or not, or a container — is a runtime's (``osmo.runtime``), as a Kubernetes pod or
a Slurm job per attempt will be; an executor of another kind implements the same five
methods. The engine owns its executors and hands each command to
the one that :meth:`~Executor.owns` the command's node; every command carries its node.

An executor reports what happens through the callable it was built with (``emit``): the
scheduler's events ``AttemptPrepared``, ``AttemptStarted``, then exactly one final report
per prepared attempt — ``AttemptExited``, ``AttemptStartFailed``, or ``AttemptLost`` when
the node that ran it went away. It never blocks its caller on a process, a disk or the
network (the engine calls it from its one thread): it queues the work and returns.

``osmo.testing.check_executor`` is the conformance kit: the same checks run over every
implementation in ``tests/test_executor_contract.py``.
"""

from __future__ import annotations

from typing import Protocol

from osmo.scheduler.types import KillAttempt, PrepareAttempt, RunAttempt
from osmo.spec.model import ResourceSpec, TaskSpec

__all__ = ["Executor"]


class Executor(Protocol):
    """Runs the attempts placed on the nodes it owns (see the module docstring)."""

    def owns(self, node_id: str) -> bool:
        """Whether attempts placed on ``node_id`` are this executor's to run."""

    def prepare(self, cmd: PrepareAttempt, task: TaskSpec, *,
                max_output_bytes: int | None = None,
                resources: ResourceSpec | None = None) -> None:
        """Make the attempt ready on ``cmd.node_id``.

        ``AttemptPrepared`` follows (and, with ``cmd.run``, the start at once), or a final report
        saying why it cannot run.

        Args:
            cmd: the placement: attempt, node, inputs, peers' addresses, whether to start.
            task: the task's definition (command or type, files, resources, outputs).
            max_output_bytes: the task's ``storage`` request; a larger output fails it.
            resources: the task's whole request (a container's limits and GPUs).
        """

    def run(self, cmd: RunAttempt) -> None:
        """Start a prepared attempt (its group's barrier was released).

        ``AttemptStarted``, then its final report; a start failure if it was not prepared here.
        """

    def kill(self, cmd: KillAttempt) -> None:
        """Stop an attempt; its final report still follows.

        Unknown or ended attempts are ignored.
        """

    def close(self) -> None:
        """Stop executing and reporting (the server is shutting down).

        What still runs is the executor's to settle: the local pool kills its processes (a restarted
        server finds those attempts lost), remote workers keep running theirs and report them to the
        next server.
        """
