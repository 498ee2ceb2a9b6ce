"""Fixtures for the tests that need a real Slurm cluster (tests/slurm/cluster.py).

- ``slurm_session`` (session): one private cluster (munged, slurmctld, nodes n1 and n2) for
  the whole session, stopped at the end (nothing of it may be left running).
- ``slurm``: that cluster for one test; afterwards every job is cancelled and every node a
  test killed is started again, so the next test finds n1 and n2 idle.

Without Slurm's programs (Debian: slurm-wlm munge; ``./dev test`` installs them) or without
root (the daemons and the nodes' namespaces need it) the tests are skipped, and a full run
(``OSMO_NO_SKIPS=1``) fails on the missing programs: only the root skip is allowed there.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.containers.conftest import (  # noqa: F401 - for the tutorials through Slurm
    engine,
    images,
    podman_env,
)
from tests.slurm.cluster import SlurmCluster
from tests.slurm.grid import (  # noqa: F401 - the session's Slurm worker
    grid,
    require_slurm,
    roomy,
)


@pytest.fixture(scope="session")
def slurm_session() -> Iterator[SlurmCluster]:
    """The session's cluster, started on first use."""
    require_slurm()
    cluster = SlurmCluster().start()
    try:
        yield cluster
    finally:
        left = cluster.stop()
        assert not left, f"still running after the Slurm cluster stopped: {left}"


@pytest.fixture
def slurm(slurm_session: SlurmCluster) -> Iterator[SlurmCluster]:
    """The session's cluster, back to idle nodes and no jobs after the test."""
    yield slurm_session
    slurm_session.reset()
