"""WorkflowGraph: edges from task inputs, order, cascades, defensive errors."""

from __future__ import annotations

import pytest

from osmo.graph import WorkflowGraph
from osmo.spec.model import InputSpec, TaskSpec

from .sim import group, task, workflow

DIAMOND = workflow(task("a"), task("b", "a"), task("c", "a"), task("d", "b", "c"))


@pytest.mark.parametrize(("name", "up", "children", "down"), [
    ("a", set(), {"b", "c"}, {"b", "c", "d"}),
    ("b", {"a"}, {"d"}, {"d"}),
    ("c", {"a"}, {"d"}, {"d"}),
    ("d", {"b", "c"}, set(), set()),
])
def test_diamond_edges(name: str, up: set[str], children: set[str], down: set[str]) -> None:
    graph = WorkflowGraph.from_spec(DIAMOND)
    assert graph.upstream(name) == up
    assert graph.children(name) == children
    assert graph.downstream(name) == down


def test_groups_map_tasks_and_order_is_topological_with_spec_ties() -> None:
    spec = workflow(task("z", "y"), group("g", task("x"), task("y", "w")), task("w"))
    graph = WorkflowGraph.from_spec(spec)
    assert graph.group_of("y") == "g"
    assert graph.upstream("z") == {"g"}
    assert graph.topological_order() == ("w", "g", "z")
    assert graph.groups == ("z", "g", "w")
    assert graph.index("w") == 2


def test_other_workflow_inputs_make_no_edge() -> None:
    t = TaskSpec("b", inputs=(InputSpec(task="a", workflow="other-1"), InputSpec(url="s3://x")))
    graph = WorkflowGraph.from_spec(workflow(task("a"), t))
    assert graph.upstream("b") == frozenset()


@pytest.mark.parametrize(("spec", "message"), [
    (workflow(task("a", "b"), task("b", "a")), "cycle among groups: a, b"),
    (workflow(task("a", "ghost")), "unknown task 'ghost'"),
    (workflow(group("g", task("a"), task("b", "a"))), "its own group 'g'"),
])
def test_invalid_graphs_raise(spec: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        WorkflowGraph.from_spec(spec)  # type: ignore[arg-type]


def test_graph_is_read_only() -> None:
    graph = WorkflowGraph.from_spec(DIAMOND)
    with pytest.raises(AttributeError):
        graph.extra = 1  # type: ignore[attr-defined]
    with pytest.raises(TypeError):
        graph._up["a"] = frozenset()  # type: ignore[index]
