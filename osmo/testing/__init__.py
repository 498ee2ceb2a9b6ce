"""Conformance kits, one per extension point: what a new implementation must pass to be done.

- :func:`check_task_type` — for task-type authors (``osmo.testing.task_types``);
- :func:`check_executor` — for executors, ``osmo.executor.Executor``: the local pool, the
  remote-worker hub, the Kubernetes or Slurm executors to come (``osmo.testing.executors``);
- :func:`check_runtime` — for runtimes, ``osmo.runtime.api.Runtime``: processes, sandboxed
  or not, containers, and the pod or batch-job runtimes to come (``osmo.testing.runtimes``).

Each checks what osmo relies on, the way osmo uses it, and fails with an ``AssertionError``
listing every problem found. Importing this package loads none of osmo's engine.
"""

from osmo.testing.executors import EventSource, check_executor
from osmo.testing.runtimes import check_runtime
from osmo.testing.task_types import check_task_type

__all__ = ["EventSource", "check_executor", "check_runtime", "check_task_type"]
