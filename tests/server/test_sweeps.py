"""The server's bookkeeping of what nodes down for good left (``osmo.server.sweeps``)."""

from __future__ import annotations

from osmo.server.sweeps import Sweeps


def test_a_node_down_for_good_is_swept_once_by_its_own_pool() -> None:
    sweeps = Sweeps()
    sweeps.registered("a", "gpu", "inst-a")
    sweeps.registered("b", "gpu", "inst-b")
    sweeps.registered("c", "cpu", "inst-c")
    assert sweeps.due("gpu") == []
    sweeps.down("a")
    assert sweeps.due("cpu") == []  # another pool (another namespace) never sweeps it
    assert sweeps.due("gpu") == ["inst-a"]
    assert sweeps.due("gpu") == []  # ordered once
    assert sweeps.sweeper("b") and not sweeps.sweeper("a")


def test_a_node_back_under_its_instance_is_not_swept() -> None:
    sweeps = Sweeps()
    sweeps.registered("a", "gpu", "inst-a")
    sweeps.down("a")
    sweeps.registered("a2", "gpu", "inst-a")  # the StatefulSet's replacement: same instance
    assert sweeps.due("gpu") == []  # it cleans up after itself


def test_a_node_without_cluster_objects_is_no_sweeper() -> None:
    sweeps = Sweeps()
    sweeps.registered("local", "gpu", None)
    sweeps.down("local")
    assert not sweeps.sweeper("local") and sweeps.due("gpu") == []


def test_a_node_cannot_get_a_live_nodes_instance_swept() -> None:
    """Hostile: a node of another pool registers under a live node's instance, then goes
    down for good: nothing is swept, in its pool or the live node's."""
    sweeps = Sweeps()
    sweeps.registered("victim", "gpu", "inst-v")
    sweeps.registered("rogue", "cpu", "inst-v")
    sweeps.down("rogue")
    assert sweeps.due("cpu") == [] and sweeps.due("gpu") == []
