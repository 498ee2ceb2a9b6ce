"""A server and an ``osmo worker --runtime slurm`` on a real Slurm cluster, for a session.

``roomy``: a cluster of its own (tests/slurm/cluster.py) whose two nodes have 2 GiB each
(OSMO's tutorials ask for 1Gi), started once (0.2 s). ``grid``: a server and the worker
``login`` (``tests.e2e.cluster.Cluster``) submitting to it, podman for image tasks (the
offline test images). Test modules import both fixtures. ``require_slurm``: the skip
every Slurm fixture starts with.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator

import pytest

from tests.e2e.cluster import Cluster
from tests.slurm.cluster import SlurmCluster, missing_programs

WORKER = "login"


def require_slurm() -> None:
    """Skip unless this process may run a cluster (root, and Slurm's programs present)."""
    if os.geteuid() != 0:
        pytest.skip("needs root: the Slurm test cluster (its daemons, the nodes' namespaces)")
    missing = missing_programs()
    if missing:
        pytest.skip(f"Slurm is not installed (missing {', '.join(missing)}); "
                    "./dev test installs it: apt-get install slurm-wlm munge")


@pytest.fixture(scope="session")
def roomy() -> Iterator[SlurmCluster]:
    """A cluster whose two nodes have 2 GiB each (OSMO's tutorials ask for 1Gi)."""
    require_slurm()
    cluster = SlurmCluster(memory_mb=2048).start()
    try:
        yield cluster
    finally:
        assert not cluster.stop(), "the cluster left processes"


@pytest.fixture(scope="session")
def grid(roomy: SlurmCluster, podman_env: dict[str, str], images: dict[str, str],
         tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    """A server and one ``osmo worker --runtime slurm`` (podman for image tasks)."""
    root = tmp_path_factory.mktemp("slurm-grid")
    made = Cluster(root, env={"SLURM_CONF": str(roomy.conf), "PATH": roomy.env["PATH"],
                              "CONTAINERS_CONF": podman_env["CONTAINERS_CONF"]})
    made.start_server()
    start_login(made)
    try:
        yield made
    finally:
        made.stop()


def start_login(grid: Cluster) -> None:
    """Start (or start again) the grid's Slurm worker; wait until it is online."""
    grid.start_worker(WORKER, "--runtime", "slurm")


def jobs_of(cluster: SlurmCluster) -> list[str]:
    """Every job the cluster still runs or queues (``ID STATE NAME``)."""
    return cluster.run("squeue", "-h", "-o", "%i %T %j").stdout.split("\n")[:-1]


def logs(grid: Cluster, wf_id: str) -> str:
    """``osmo logs`` of the workflow."""
    return grid.osmo("logs", wf_id, check=True).out


def until_logged(grid: Cluster, wf_id: str, text: str, timeout: float = 90) -> str:
    """The workflow's logs once they hold ``text``."""
    deadline = time.monotonic() + timeout
    while text not in (seen := logs(grid, wf_id)):
        assert time.monotonic() < deadline, f"never logged {text!r}:\n{seen}"
        time.sleep(0.2)
    return seen


def until_no_job(cluster: SlurmCluster, name_part: str, timeout: float = 30) -> None:
    """Wait until no job whose id is ``name_part``, or whose name holds it (a name part
    that is not a job id: digits would match a name's digest), is queued or running."""
    deadline = time.monotonic() + timeout
    while any(name_part == line.split()[0]
              or (not name_part.isdigit() and name_part in line.split()[-1])
              for line in jobs_of(cluster)):
        assert time.monotonic() < deadline, f"a job is left: {jobs_of(cluster)}"
        time.sleep(0.2)
