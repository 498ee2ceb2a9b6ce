"""osmo's adapter of Slurm's commands (osmo.runtime.slurm.commands) against a real cluster."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

from osmo.runtime.slurm import Slurm, SlurmError
from osmo.runtime.slurm.commands import takes_jobs
from tests.slurm.cluster import SlurmCluster
from tests.slurm.grid import require_slurm


@pytest.fixture(scope="module")
def two_partitions() -> Iterator[SlurmCluster]:
    """A cluster whose nodes are in two partitions (``debug`` and ``other``)."""
    require_slurm()
    cluster = SlurmCluster(extra_conf=["PartitionName=other Nodes=n1,n2 State=UP"]).start()
    try:
        yield cluster
    finally:
        assert not cluster.stop()


def test_capacity_counts_each_node_once_across_partitions(
        two_partitions: SlurmCluster) -> None:
    slurm = Slurm(two_partitions.env)
    both = slurm.capacity(("debug", "other"))
    assert (both.cpus, both.memory, both.gpus, both.nodes) == (4, 1000 << 20, 2, 2), both
    assert slurm.capacity(()).cpus == 4
    assert slurm.capacity(("other",)).name == "other"


def test_a_failing_command_says_which_and_why_and_a_forgotten_job_is_just_missing(two_partitions: SlurmCluster) -> None:
    slurm = Slurm(two_partitions.env)
    with pytest.raises(SlurmError, match="scancel .*Invalid job id"):
        slurm.cancel("not-a-job")
    assert slurm.jobs(["999999"]) == {}
    job = two_partitions.sbatch("sleep 30")
    try:  # one job slurmctld forgot does not hide the others
        assert list(slurm.jobs([job, "999999"])) == [job]
    finally:
        two_partitions.run("scancel", job)


def test_a_node_that_takes_no_jobs_adds_no_capacity_until_it_is_resumed(
        two_partitions: SlurmCluster) -> None:
    slurm = Slurm(two_partitions.env)
    two_partitions.run("scontrol", "update", "NodeName=n1", "State=DRAIN", "Reason=maintenance")
    try:
        drained = slurm.capacity(("debug", "other"))
        assert (drained.cpus, drained.gpus, drained.nodes, drained.listed) == (2, 1, 1, 2), drained
        assert slurm.partitions(("other",))["other"].cpus == 2
        two_partitions.run("scontrol", "update", "NodeName=n2", "State=DRAIN", "Reason=too")
        none = slurm.capacity(())  # every node drained: the partition is there, empty
        assert (none.cpus, none.memory, none.nodes, none.listed) == (0, 0, 0, 2), none
    finally:
        two_partitions.run("scontrol", "update", "NodeName=n1,n2", "State=RESUME")
    deadline = time.monotonic() + 30  # resumed, each is "idle*" until slurmctld reached it
    while (back := slurm.capacity(("debug", "other"))).nodes < 2:
        assert back.listed == 2 and time.monotonic() < deadline, back
        time.sleep(0.2)
    assert (back.cpus, back.nodes) == (4, 2), back


def test_a_pool_that_names_no_partition_counts_the_default_partition_only(
        two_partitions: SlurmCluster) -> None:
    """A job that names no partition goes to Slurm's default one: only its nodes (and its
    time limit) are what such a pool has, not every partition's."""
    slurm = Slurm(two_partitions.env)
    two_partitions.run("scontrol", "update", "PartitionName=debug", "Default=NO")
    two_partitions.run("scontrol", "create", "PartitionName=small", "Nodes=n1", "Default=YES",
                       "MaxTime=7", "State=UP")
    try:
        small = slurm.capacity(())
        assert (small.name, small.cpus, small.nodes, small.listed) == ("small", 2, 1, 1), small
        assert slurm.max_minutes(()) == 7
        both = slurm.capacity(("debug", "small"))  # named, as before
        assert (both.cpus, both.nodes) == (4, 2), both
    finally:
        two_partitions.run("scontrol", "delete", "PartitionName=small")
        two_partitions.run("scontrol", "update", "PartitionName=debug", "Default=YES")
    assert slurm.capacity(()).cpus == 4


@pytest.mark.parametrize(("state", "takes"), [
    ("idle", True), ("mixed", True), ("allocated", True), ("completing", True),
    ("idle~", True), ("idle#", True), ("planned", True), ("mixed-", True),
    ("drained", False), ("draining", False), ("down", False), ("down*", False),
    ("idle*", False), ("fail", False), ("failing", False), ("reserved", False),
    ("maint", False), ("reboot_issued", False), ("unknown", False), ("future", False),
    ("inval", False), ("", False), ("idle+cloud", True), ("mixed+drain", False),
    ("allocated+completing", True), ("idle~+power_down", True), ("idle+maint", False),
    ("MIXED", True)])
def test_which_node_states_take_jobs(state: str, takes: bool) -> None:
    assert takes_jobs(state) is takes
