"""The server's bookkeeping of what nodes down for good left (``osmo.server.sweeps``)."""

from __future__ import annotations

from pathlib import Path

from osmo.server.sweeps import Sweeps
from osmo.store.sqlite import Store


def test_a_node_down_for_good_is_swept_by_its_own_pool_one_node_at_a_time() -> None:
    sweeps = Sweeps()
    sweeps.registered("a", "gpu", "inst-a")
    sweeps.registered("b", "gpu", "inst-b")
    sweeps.registered("d", "gpu", "inst-d")
    sweeps.registered("c", "cpu", "inst-c")
    assert sweeps.due("gpu", "b") == []
    sweeps.down("a")
    assert sweeps.due("cpu", "c") == []  # another pool (another namespace) never sweeps it
    assert sweeps.due("gpu", "b") == ["inst-a"]
    assert sweeps.due("gpu", "d") == []  # ordered to b until b says it is done
    assert sweeps.sweeper("b") and not sweeps.sweeper("a")
    assert not sweeps.swept("d", "inst-a")  # not ordered to d: refused, still b's
    assert not sweeps.swept("b", "inst-b")  # never ordered at all
    assert sweeps.swept("b", "inst-a")
    assert sweeps.release("b") == [] and sweeps.due("gpu", "d") == []  # done for good


def test_what_a_node_did_not_sweep_goes_to_another_when_it_leaves() -> None:
    sweeps = Sweeps()
    sweeps.registered("a", "gpu", "inst-a")
    sweeps.registered("b", "gpu", "inst-b")
    sweeps.down("a")
    assert sweeps.due("gpu", "b") == ["inst-a"]
    assert sweeps.release("b") == ["gpu"]  # b left (or registered again) before it swept
    assert not sweeps.swept("b", "inst-a")  # a late word of b counts no more
    assert sweeps.due("gpu", "c") == ["inst-a"]
    assert sweeps.swept("c", "inst-a")


def test_an_unconfirmed_order_is_due_to_its_node_again_after_the_retry_period() -> None:
    sweeps = Sweeps()
    sweeps.registered("a", "gpu", "inst-a")
    sweeps.registered("b", "gpu", "inst-b")
    sweeps.down("a")
    assert sweeps.due("gpu", "b") == ["inst-a"]
    assert sweeps.overdue(60) == []  # just sent
    assert sweeps.overdue(0) == [("b", "inst-a")]  # to b again, and counted as sent now
    assert sweeps.overdue(60) == []
    assert sweeps.swept("b", "inst-a") and sweeps.overdue(0) == []  # confirmed: done


def test_a_node_back_under_its_instance_is_not_swept() -> None:
    sweeps = Sweeps()
    sweeps.registered("a", "gpu", "inst-a")
    sweeps.down("a")
    sweeps.registered("a2", "gpu", "inst-a")  # the StatefulSet's replacement: same instance
    assert sweeps.due("gpu", "a2") == []  # it cleans up after itself


def test_a_node_without_cluster_objects_is_no_sweeper() -> None:
    sweeps = Sweeps()
    sweeps.registered("local", "gpu", None)
    sweeps.down("local")
    assert not sweeps.sweeper("local") and sweeps.due("gpu", "b") == []


def test_a_node_cannot_get_a_live_nodes_instance_swept() -> None:
    """Hostile: a node of another pool registers under a live node's instance, then goes
    down for good: nothing is swept, in its pool or the live node's."""
    sweeps = Sweeps()
    sweeps.registered("victim", "gpu", "inst-v")
    sweeps.registered("rogue", "cpu", "inst-v")
    sweeps.down("rogue")
    assert sweeps.due("cpu", "x") == [] and sweeps.due("gpu", "victim") == []


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
    assert again.due("cpu", "c") == []
    assert again.due("gpu", "e") == ["inst-a", "inst-b"]
    assert again.swept("e", "inst-b")  # said done; inst-a never was
    third = Sweeps(Store(tmp_path / "state.db"))
    assert third.due("gpu", "f") == ["inst-a"]  # ordered again: nobody said it was swept
    assert third.restored() == {"c"} and third.sweeper("c")


def test_a_restored_node_back_under_its_instance_is_not_swept(tmp_path: Path) -> None:
    Sweeps(Store(tmp_path / "state.db")).registered("a", "gpu", "inst-a")
    sweeps = Sweeps(Store(tmp_path / "state.db"))
    sweeps.registered("a", "gpu", "inst-a")  # back within the grace
    sweeps.down("gone-other")  # unknown: nothing
    assert sweeps.due("gpu", "a") == []
