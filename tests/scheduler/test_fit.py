"""check_fit reasons and placement constraints (pool, platform, nodesExcluded)."""

from __future__ import annotations

import pytest

from osmo.scheduler import Scheduler
from osmo.spec.model import ResourceSpec

from .sim import GiB, Sim, group, node, task, workflow


def sched(*nodes: object) -> Scheduler:
    return Sim(*nodes).s  # type: ignore[arg-type]


R = ResourceSpec


@pytest.mark.parametrize(("resources", "pool", "reasons"), [
    ({}, "local", []),
    ({}, None, []),
    ({"default": R(cpu=4, gpu=0)}, "local", []),
    ({}, "x", ["unknown pool 'x' (pools: gpu, local)"]),
    ({"default": R(gpu=1)}, "local",
     ["task 'train' requests gpu=1 but no node in pool 'local' has more than 0 gpu",
      "task 'eval' requests gpu=1 but no node in pool 'local' has more than 0 gpu"]),
    ({"default": R(gpu=1)}, None, []),  # the gpu pool has one
    ({"default": R(memory=64 * GiB)}, "local",
     ["task 'train' requests memory=64Gi but no node in pool 'local' has more than 16Gi "
      "memory", "task 'eval' requests memory=64Gi but no node in pool 'local' has more than "
      "16Gi memory"]),
    ({"default": R(platform="jetson")}, "local",
     ["task 'train' requests platform 'jetson' but no node in pool 'local' has it "
      "(platforms: x86)"] * 1 + ["task 'eval' requests platform 'jetson' but no node in pool "
                                 "'local' has it (platforms: x86)"]),
    ({"default": R(nodes_excluded=("l1", "l2"))}, "local",
     ["task 'train' excludes every eligible node in pool 'local'",
      "task 'eval' excludes every eligible node in pool 'local'"]),
    ({"default": R(cpu=3, memory=10 * GiB)}, "local",
     ["task 'train' requests cpu=3, memory=10Gi but no single node in pool 'local' has all "
      "of it", "task 'eval' requests cpu=3, memory=10Gi but no single node in pool 'local' "
      "has all of it"]),
])
def test_check_fit_of_single_tasks(resources: dict[str, ResourceSpec], pool: str | None,
                                   reasons: list[str]) -> None:
    s = sched(node("l1", cpu=4, memory=8 * GiB, platform="x86"),
              node("l2", cpu=2, memory=16 * GiB, platform="x86"),
              node("g1", cpu=8, gpu=1, memory=64 * GiB, pool="gpu"))
    spec = workflow(task("train"), task("eval", "train"), resources=resources)
    assert s.check_fit(spec, pool) == reasons


@pytest.mark.parametrize(("sizes", "reasons"), [
    ((1, 1), []),
    ((2, 2), []),  # spreads over both nodes
    ((2, 2, 1), ["group 'g' needs cpu=5 at once; the largest placement possible is 4"]),
    ((3, 1), ["task 't0' requests cpu=3 but no node in pool 'local' has more than 2 cpu"]),
    ((2, 1, 1), []),
    ((1, 1, 1, 1), []),
    ((1, 1, 1, 1, 1), ["group 'g' needs cpu=5 at once; the largest placement possible is 4"]),
])
def test_check_fit_of_gangs(sizes: tuple[int, ...], reasons: list[str]) -> None:
    s = sched(node("n1", cpu=2), node("n2", cpu=2))
    resources = {f"r{i}": R(cpu=c) for i, c in enumerate(sizes)}
    tasks = [task(f"t{i}", resource=f"r{i}", lead=i == 0) for i in range(len(sizes))]
    assert s.check_fit(workflow(group("g", *tasks), resources=resources), "local") == reasons


def test_check_fit_ignores_current_usage_and_reports_packing_failures() -> None:
    s = sched(node("n1", cpu=3), node("n2", cpu=3))
    sizes = {"two": R(cpu=2)}
    spec = workflow(group("g", *[task(f"t{i}", resource="two", lead=i == 0) for i in range(3)]),
                    resources=sizes)
    assert s.check_fit(spec, "local") == [
        "group 'g' needs cpu=6 at once but its 3 tasks cannot be packed onto the nodes of "
        "pool 'local'"]


def test_check_fit_without_nodes() -> None:
    assert Scheduler().check_fit(workflow(task("t")), None) == [
        "no node is available in any pool"]


def test_placement_honours_pool_platform_and_exclusions() -> None:
    sim = Sim(node("a1", pool="p1"), node("b1", platform="arm"), node("c1"))
    resources = {"default": R(), "arm": R(platform="arm"), "not-c": R(nodes_excluded=("a1",
                                                                                       "c1"))}
    spec = workflow(task("any"), task("arm", resource="arm"), task("notc", resource="not-c"),
                    resources=resources)
    sim.submit(spec, pool="local")
    assert {t.name: t.node_id for t in sim.s.tasks("wf-1")} == {
        "any": "b1", "arm": "b1", "notc": "b1"}
    sim.submit(workflow(task("p")), wid="wf-2", pool="p1")
    assert sim.task("p", "wf-2").node_id == "a1"
    sim.submit(workflow(task("q")), wid="wf-3", pool="nowhere")
    assert sim.status("q", "wf-3") == "SCHEDULING"


def two_platforms(node_id: str = "k1") -> object:
    """A cluster node: 16 cpu in all, 4 of them (and 2 gpus) on its gpu nodes."""
    from osmo.scheduler.types import Capacity, Node
    return Node(node_id, "local", Capacity(16, 2, 64 * GiB, 100 * GiB), address="a",
                platforms={"gpu": Capacity(4, 2, 16 * GiB, 100 * GiB),
                           "cpu": Capacity(12, 0, 48 * GiB, 100 * GiB)})


@pytest.mark.parametrize(("resources", "reasons"), [
    ({"default": R(platform="gpu", cpu=4, gpu=2)}, []),
    ({"default": R(platform="cpu", cpu=12)}, []),
    ({"default": R(platform="gpu", cpu=8)},
     ["task 'a' requests cpu=8 but no node in pool 'local' has more than 4 cpu",
      "task 'b' requests cpu=8 but no node in pool 'local' has more than 4 cpu"]),
    ({"default": R(platform="cpu", gpu=1)},
     ["task 'a' requests gpu=1 but no node in pool 'local' has more than 0 gpu",
      "task 'b' requests gpu=1 but no node in pool 'local' has more than 0 gpu"]),
    ({"default": R(platform="arm")},
     ["task 'a' requests platform 'arm' but no node in pool 'local' has it "
      "(platforms: cpu, gpu)", "task 'b' requests platform 'arm' but no node in pool "
      "'local' has it (platforms: cpu, gpu)"]),
])
def test_a_node_with_platforms_offers_each_its_own_capacity(resources: dict,
                                                            reasons: list[str]) -> None:
    spec = workflow(task("a"), task("b"), resources=resources)
    assert sched(two_platforms()).check_fit(spec, "local") == reasons


def test_tasks_fill_each_platform_apart_and_wait_for_their_own() -> None:
    sim = Sim(two_platforms())
    spec = workflow(task("g1", resource="g"), task("g2", resource="g"),
                    task("c1", resource="c"), task("c2", resource="c"),
                    resources={"g": R(platform="gpu", cpu=3, gpu=1),
                               "c": R(platform="cpu", cpu=6)})
    sim.submit(spec)
    # the gpu platform has 4 cpus: one gpu task at a time; the cpu platform takes both
    assert sim.statuses() == {"g1": "INITIALIZING", "g2": "SCHEDULING",
                              "c1": "INITIALIZING", "c2": "INITIALIZING"}
    waiting = sim.s.waiting("wf-1")["g2"].reason
    assert waiting == "needs 3 cpu, largest free is 1", waiting
    assert (sim.s.used("k1").cpu, sim.s.used("k1", "gpu").cpu) == (15, 3)
    sim.run("g1")
    assert sim.status("g2") == "INITIALIZING"
    assert sim.s.used("k1", "gpu").cpu == 3


def test_a_worker_of_one_platform_still_serves_it_with_its_whole_capacity() -> None:
    sim = Sim(node("n1", cpu=4, platform="x86"))
    sim.submit(workflow(task("a"), task("b"), resources={"default": R(platform="x86", cpu=2)}))
    assert sim.statuses() == {"a": "INITIALIZING", "b": "INITIALIZING"}
