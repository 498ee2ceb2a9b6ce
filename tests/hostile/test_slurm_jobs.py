"""Hostile input against the Slurm executor: user text must never become Slurm's or a
shell's (osmo.runtime.slurm.script), and a credential must reach only its job.

A task whose environment value holds a newline and a ``#SBATCH`` directive, command
substitutions and a quote-breaking argument runs with them as plain data: the batch script
``scontrol write batch_script`` shows is osmo's fixed text, the job keeps the memory osmo
asked for, nothing the text names is run, and neither the text nor the credential appears
in ``scontrol show job -d`` or in the batch script.
"""

from __future__ import annotations

import hashlib
import shlex
import time
import uuid
from pathlib import Path

import pytest

from osmo.runtime.api import PrepareError
from osmo.runtime.slurm.script import batch_script, job_name
from tests.conftest import write
from tests.containers.conftest import images, podman_env  # noqa: F401 - the grid's
from tests.e2e.cluster import Cluster
from tests.slurm.cluster import SlurmCluster
from tests.slurm.grid import grid, jobs_of, logs, roomy, until_logged  # noqa: F401 - the grid's

SECRET = f"slurm-s3cr3t-{uuid.uuid4().hex[:12]}"


def sha(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def test_the_batch_script_is_fixed_text_whatever_the_paths_hold(tmp_path: Path) -> None:
    folder = tmp_path / "a'b $(touch x) `y`;#SBATCH --mem=1"
    script = batch_script("/usr/bin/python3", Path("/opt/agent.py"), folder)
    lines = script.splitlines()
    assert lines[0] == "#!/bin/sh" and len(lines) == 2, script
    assert lines[1].startswith("exec /usr/bin/python3 -I /opt/agent.py '"), script
    assert shlex.split(lines[1])[-1] == str(folder)  # one word, as it is
    with pytest.raises(PrepareError, match="control character"):
        batch_script("/usr/bin/python3", Path("/opt/agent.py"), tmp_path / "a\n#SBATCH -N9")
    name = job_name("t$(x)\n#SBATCH", "wf:t:0")
    assert name.startswith("osmo-t__x___SBATCH-") and name.replace("-", "").replace(
        "_", "").isalnum(), name


@pytest.fixture
def slurm_grid(request: pytest.FixtureRequest) -> tuple[Cluster, SlurmCluster]:
    """The session's Slurm worker and its cluster (tests/slurm/grid.py)."""
    return request.getfixturevalue("grid"), request.getfixturevalue("roomy")


def test_user_text_stays_data_and_the_credential_stays_out_of_slurm(
        slurm_grid: tuple[Cluster, SlurmCluster], tmp_path: Path) -> None:
    server, cluster = slurm_grid
    marker = tmp_path / "pwned"
    nasty = f"a\n#SBATCH --mem=1\n$(touch {marker}) `touch {marker}`; touch {marker}"
    argument = f"'; touch {marker} #\n#SBATCH --mem=1"
    gate = tmp_path / "gate"
    server.osmo("credential", "set", "api", "--payload", f"token={SECRET}", check=True)
    spec = write(tmp_path / "wf.yaml", f"""
workflow:
  name: nasty
  resources:
    default: {{cpu: 1, memory: 100Mi}}
  tasks:
  - name: nasty
    command: [sh, -c, 'printf %s "$NASTY" | sha256sum; printf %s "$1" | sha256sum;
      case "$TOKEN" in slurm-s3cr3t-*) echo has-token;; esac; echo up;
      while [ ! -e {gate} ]; do sleep 0.2; done', sh, {_yaml(argument)}]
    environment: {{NASTY: {_yaml(nasty)}}}
    credentials:
      api: {{TOKEN: token}}
""")
    wf_id = server.osmo.submit(spec)
    try:
        until_logged(server, wf_id, "[nasty] up")
        job = next(line.split()[0] for line in jobs_of(cluster) if "osmo-nasty-" in line)
        shown = cluster.run("scontrol", "show", "job", "-d", job).stdout
        script = cluster.run("scontrol", "write", "batch_script", job, "-").stdout
    finally:
        gate.touch()
    info = server.osmo.wait_for(wf_id, lambda i: i["status"] == "COMPLETED", timeout=90)
    assert "MinMemoryNode=100M" in shown, shown  # osmo's --mem, not the text's
    assert script.startswith("#!/bin/sh\nexec ") and len(script.splitlines()) == 2, script
    for text in (SECRET, "pwned", "SBATCH", "NASTY"):
        assert text not in shown + script, (text, shown, script)
    said = logs(server, wf_id)
    assert f"[nasty] {sha(nasty)}  -" in said and f"[nasty] {sha(argument)}  -" in said, said
    assert "[nasty] has-token" in said and SECRET not in said, said
    time.sleep(0.5)
    assert not marker.exists(), info


def _yaml(text: str) -> str:
    """``text`` as a double-quoted YAML scalar."""
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
