"""A task cannot see the control plane: the server's environment, OSMO_HOME, its state store.

End to end through the CLI with the default server (the process sandbox is on wherever
bubblewrap works, as here).
"""

from __future__ import annotations

import shutil
from pathlib import Path

from tests.conftest import Osmo, ended, write
from tests.e2e.cluster import Cluster

MARKER = "server-only-7c1d9e"

SNOOP = """
workflow:
  name: snoop
  tasks:
  - name: look
    command: [sh, -c, 'env > {{output}}/env;
      if cat "$DB" > /dev/null 2>&1; then echo readable; else echo hidden; fi > {{output}}/db;
      ls -a "$HOME_DIR" > {{output}}/home 2>&1; exit 0']
    environment:
      DB: "@HOME@/state.db"
      HOME_DIR: "@HOME@"
"""


def _run(osmo: Osmo, spec: Path) -> dict:
    info = osmo.wait_for(osmo.submit(spec), ended)
    assert info["status"] == "COMPLETED", info
    return info


def test_task_sees_no_server_environment_nor_its_home(osmo: Osmo, tmp_path: Path) -> None:
    assert shutil.which("bwrap"), "bubblewrap must be installed (./dev test installs it)"
    osmo.env["OSMO_TEST_SERVER_MARKER"] = MARKER  # the auto-started server inherits it
    home = str(osmo.home.absolute())
    info = _run(osmo, write(tmp_path / "snoop.yaml", SNOOP.replace("@HOME@", home)))
    out = Path(info["tasks"][0]["output"])
    env = dict(line.split("=", 1) for line in (out / "env").read_text().splitlines()
               if "=" in line)
    assert MARKER not in (out / "env").read_text()
    assert "OSMO_HOME" not in env and "OSMO_TEST_SERVER_MARKER" not in env
    assert env["OSMO_TASK"] == "look" and env["PATH"]  # the documented base is there
    assert (out / "db").read_text() == "hidden\n"
    listing = (out / "home").read_text().split()
    assert "state.db" not in listing and "artifacts" not in listing, listing


def test_a_worker_task_sees_neither_its_workers_home_nor_the_servers(tmp_path: Path) -> None:
    """A worker on the server's host hides the server's home too (it learns it on register)."""
    cluster = Cluster(tmp_path)
    try:
        cluster.start_server()
        cluster.start_worker("w1")
        spec = write(tmp_path / "snoop.yaml", f"""
workflow:
  name: snoop
  tasks:
  - name: look
    command: [sh, -c, 'for f in {tmp_path}/server/state.db {tmp_path}/w1/worker/worker.json; do
      if cat "$f" > /dev/null 2>&1; then echo "readable $f"; else echo hidden; fi;
      done > {{{{output}}}}/seen']
""")
        assert (tmp_path / "server" / "state.db").exists()
        assert (tmp_path / "w1" / "worker" / "worker.json").exists()
        wf = cluster.osmo.submit(spec)
        assert cluster.osmo.wait_for(wf, ended)["status"] == "COMPLETED"
        cluster.osmo("artifacts", "get", f"{wf}:look", "-o", str(tmp_path / "got"), check=True)
        assert (tmp_path / "got" / "seen").read_text() == "hidden\nhidden\n"
    finally:
        cluster.stop()
