"""The server's bookkeeping of what nodes down for good left (``osmo.server.sweeps``)."""

from __future__ import annotations

from pathlib import Path

from osmo.server.sweeps import Sweeps
from osmo.store.sqlite import Store


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


def test_a_restarted_server_keeps_the_instances_and_what_is_still_to_sweep(
        tmp_path: Path) -> None:
    """Kept in the store: a new server's ``Sweeps`` on the same store (a kill -9 in between)
    still has the pending sweep, and knows the nodes of the previous life as restored."""
    store = Store(tmp_path / "state.db")
    sweeps = Sweeps(store)
    sweeps.registered("a", "gpu", "inst-a")
    sweeps.registered("b", "gpu", "inst-b")
    sweeps.registered("c", "cpu", "inst-c")
    sweeps.registered("local", "cpu", None)
    sweeps.down("a")  # no live node of gpu to order it to
    again = Sweeps(Store(tmp_path / "state.db"))
    assert again.restored() == {"b", "c"}
    again.down("b")  # not back within the grace
    assert again.due("cpu") == []
    assert again.due("gpu") == ["inst-a", "inst-b"]
    third = Sweeps(Store(tmp_path / "state.db"))
    assert third.due("gpu") == []  # ordered once, in the life that ordered it
    assert third.restored() == {"c"} and third.sweeper("c")


def test_a_restored_node_back_under_its_instance_is_not_swept(tmp_path: Path) -> None:
    Sweeps(Store(tmp_path / "state.db")).registered("a", "gpu", "inst-a")
    sweeps = Sweeps(Store(tmp_path / "state.db"))
    sweeps.registered("a", "gpu", "inst-a")  # back within the grace
    sweeps.down("gone-other")  # unknown: nothing
    assert sweeps.due("gpu") == []
