"""The DAG of a workflow's groups, built from ``inputs: - task:`` edges.

This module owns the shape of a workflow as a graph: which group each task belongs to, which
groups a group waits for, which groups a failure cascades to, and a deterministic
topological order. It holds no status and no scheduling logic, and never mutates.

An edge ``A -> B`` exists when a task of group ``B`` takes an input from a task of group
``A`` (same workflow; ``WORKFLOW_ID:NAME`` inputs point at other workflows and make no edge).
The parser rejects cycles and unknown tasks; :meth:`WorkflowGraph.from_spec` still raises
``ValueError`` for them, defensively, so an invalid model never reaches the scheduler.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterable, Mapping
from types import MappingProxyType

from osmo.spec.model import WorkflowSpec

__all__ = ["WorkflowGraph"]

_NONE: frozenset[str] = frozenset()


class WorkflowGraph:
    """An immutable DAG of groups.

    Build it with :meth:`from_spec`. Group names are returned in spec order or topological
    order (ties broken by spec order), so every walk over the graph is deterministic.
    """

    __slots__ = ("_children", "_downstream", "_group_of", "_groups", "_index", "_order", "_up")

    def __init__(self, groups: Iterable[str], group_of: Mapping[str, str],
                 upstream: Mapping[str, Iterable[str]]) -> None:
        """Build from group names (spec order), task → group, and group → upstream groups.

        Raises:
            ValueError: on an unknown group in ``upstream`` or a cycle.
        """
        self._groups = tuple(groups)
        self._index = MappingProxyType({g: i for i, g in enumerate(self._groups)})
        self._group_of = MappingProxyType(dict(group_of))
        # most groups of a big fan-out have no edge on one side: they share one empty set
        up: dict[str, frozenset[str]] = {}
        children: dict[str, set[str]] = {}
        for group in self._groups:
            ups = upstream.get(group)
            up[group] = frozenset(ups) if ups else _NONE
            for name in up[group]:
                if name not in self._index:
                    raise ValueError(f"group '{group}' depends on unknown group '{name}'")
                children.setdefault(name, set()).add(group)
        self._up = MappingProxyType(up)
        self._children = MappingProxyType({g: frozenset(c) for g, c in children.items()})
        self._order = self._topological()
        self._downstream: dict[str, frozenset[str]] = {}  # memo; derived, never observable

    @classmethod
    def from_spec(cls, spec: WorkflowSpec) -> WorkflowGraph:
        """The graph of ``spec``'s groups.

        Raises:
            ValueError: a task input names an unknown task, a task of its own group, or the
                edges form a cycle.
        """
        group_of = {t.name: g.name for g in spec.groups for t in g.tasks}
        upstream: dict[str, set[str]] = {}
        for group in spec.groups:
            for task in group.tasks:
                for name in task.upstream_tasks():
                    if name not in group_of:
                        raise ValueError(f"task '{task.name}' takes input from unknown task "
                                         f"'{name}'")
                    if group_of[name] == group.name:
                        raise ValueError(f"task '{task.name}' takes input from '{name}' of its "
                                         f"own group '{group.name}' (a cycle)")
                    upstream.setdefault(group.name, set()).add(group_of[name])
        return cls([g.name for g in spec.groups], group_of, upstream)

    @property
    def groups(self) -> tuple[str, ...]:
        """Every group name, in spec order."""
        return self._groups

    def index(self, group: str) -> int:
        """The 0-based position of ``group`` in spec order (KeyError if unknown)."""
        return self._index[group]

    def group_of(self, task: str) -> str:
        """The group that holds ``task`` (KeyError if unknown)."""
        return self._group_of[task]

    def upstream(self, group: str) -> frozenset[str]:
        """The groups ``group`` waits for directly."""
        return self._up[group]

    def children(self, group: str) -> frozenset[str]:
        """The groups that wait directly for ``group`` (KeyError if unknown)."""
        found = self._children.get(group)
        if found is None:
            self._index[group]  # noqa: B018 - raises KeyError for an unknown group
            return _NONE
        return found

    def downstream(self, group: str) -> frozenset[str]:
        """Every group that waits for ``group``, directly or transitively (for cascades)."""
        found = self._downstream.get(group)
        if found is None:
            seen: set[str] = set()
            stack = list(self.children(group))
            while stack:
                name = stack.pop()
                if name not in seen:
                    seen.add(name)
                    stack.extend(self._children.get(name, _NONE))
            found = self._downstream[group] = frozenset(seen)
        return found

    def topological_order(self) -> tuple[str, ...]:
        """Every group, upstream before downstream; ties in spec order."""
        return self._order

    def _topological(self) -> tuple[str, ...]:
        waiting = {g: len(ups) for g, ups in self._up.items()}
        ready = [self._index[g] for g, n in waiting.items() if n == 0]
        heapq.heapify(ready)
        order: list[str] = []
        while ready:
            name = self._groups[heapq.heappop(ready)]
            order.append(name)
            for child in self._children.get(name, _NONE):
                waiting[child] -= 1
                if waiting[child] == 0:
                    heapq.heappush(ready, self._index[child])
        if len(order) < len(self._groups):
            stuck = sorted((g for g, n in waiting.items() if n > 0), key=self._index.__getitem__)
            raise ValueError(f"cycle among groups: {', '.join(stuck)}")
        return tuple(order)

    def __repr__(self) -> str:
        return f"WorkflowGraph(groups={len(self._groups)})"
