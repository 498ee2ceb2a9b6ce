"""Which of a workflow's tasks a query shows, in spec order, without decoding every row.

``osmo query`` of a 100,000-task workflow must answer in well under a second while the
engine runs it. A query that names a ``limit`` or ``statuses`` gets the count of tasks per
status, how many tasks match, and the full state of only the first ``limit`` matching tasks
in spec order (groups, then the tasks within a group). Only names and statuses are read
for the rest (SQLite does that without holding the GIL for long); a workflow's spec order is
kept for the few workflows asked about last, since decoding a big spec is the dearest part.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from osmo.store.sqlite import Store

__all__ = ["Page", "TaskView", "spec_order"]

_KEPT = 8  # spec orders kept (workflows asked about last)


@dataclass(frozen=True)
class Page:
    """A query's share of a workflow's tasks.

    Attributes:
        tasks: state payloads of the tasks shown, in spec order.
        counts: status → how many of all the workflow's tasks have it.
        matched: how many tasks match the query's statuses (shown or not).
    """

    tasks: list[dict[str, Any]]
    counts: dict[str, int]
    matched: int


def spec_order(spec: dict[str, Any]) -> list[str]:
    """A stored spec's task names in order (groups' tasks after the plain tasks)."""
    wf = spec.get("workflow", {})
    names = [t["name"] for t in wf.get("tasks", [])]
    return names + [t["name"] for g in wf.get("groups", []) for t in g.get("tasks", [])]


class TaskView:
    """Pages of workflows' tasks read from ``store`` (any API thread)."""

    def __init__(self, store: Store) -> None:
        self._store = store
        self._orders: OrderedDict[str, list[str]] = OrderedDict()

    def page(self, workflow_id: str, *, limit: int | None, statuses: Sequence[str] = (),
             spec: Callable[[], dict[str, Any]]) -> Page:
        """The first ``limit`` tasks (None: all) whose status is one of ``statuses`` (all).

        ``spec`` gives the workflow's stored spec, asked only when its order is not kept.
        """
        counts = self._store.task_counts(workflow_id)
        order = self._order(workflow_id, spec)
        if statuses:  # only the names with those statuses are read, not every row
            names = self._store.task_names(workflow_id, statuses)
            matched = len(names)
            listed = [n for n in order if n in names]
            listed += sorted(names - set(listed)) if len(listed) < matched else []
        else:
            matched = sum(counts.values())
            listed = order if limit is None else order[:limit]
        shown = listed if limit is None else listed[:limit]
        position = {name: i for i, name in enumerate(shown)}
        tasks = sorted(self._store.tasks_named(workflow_id, shown),
                       key=lambda t: position[t["name"]])
        return Page(tasks, counts, matched)

    def _order(self, workflow_id: str, spec: Callable[[], dict[str, Any]]) -> list[str]:
        order = self._orders.get(workflow_id)
        if order is None:
            order = spec_order(spec())
            self._orders[workflow_id] = order
            while len(self._orders) > _KEPT:
                self._orders.popitem(last=False)
        self._orders.move_to_end(workflow_id)
        return order
