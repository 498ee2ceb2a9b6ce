"""osmo's adapter of Slurm's commands (osmo.runtime.slurm.commands) against a real cluster."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from osmo.runtime.slurm import Slurm, SlurmError
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
