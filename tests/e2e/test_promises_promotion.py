"""docs/reference/runtimes.md, Outputs: "After a successful exit, `output.partial/` is renamed
atomically to `output/`. Downstream tasks only ever see a promoted `output/`." And the rule
"no lost work": kill -9 of the server mid-run ends with the workflow correct after restart.

The server is SIGKILLed while it promotes an output of 4,000 files: on its own host (the
rename, then the ingest into the artifact store), and while it takes a remote worker's
output in (the blobs, then the folder of links under ``runs/``). At that instant the output
folder must be absent or complete; after the restart the downstream task must see all of it.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable
from pathlib import Path

from tests.conftest import Osmo, ended, wait_gone, write
from tests.e2e.cluster import Cluster

FILES = 4000

SPEC = """
workflow:
  name: promote
  tasks:
  - name: make
    command: [sh, -c, "for i in $(seq FILES); do echo $i > {{output}}/f$i; done"]
  - name: use
    command: [sh, -c, "cat {{input:make}}/f* | awk '{s += $1} END {print NR, s}' > {{output}}/seen"]
    inputs:
    - task: make
""".replace("FILES", str(FILES))
EVERYTHING = f"{FILES} {FILES * (FILES + 1) // 2}\n"


def _kill_when(pid: int, seen: Callable[[], bool], timeout: float = 120) -> None:
    """SIGKILL ``pid`` the moment ``seen()`` holds (polled as fast as this process can)."""
    deadline = time.monotonic() + timeout
    while not seen():
        assert time.monotonic() < deadline, "the promotion never started"
        time.sleep(0.0005)
    os.kill(pid, signal.SIGKILL)
    wait_gone(pid)


def _nothing_or_everything(folder: Path) -> None:
    if folder.exists():
        names = os.listdir(folder)
        assert len(names) == FILES, f"{folder} is visible with {len(names)} of {FILES} files"


def _downstream_saw_everything(osmo: Osmo, wf: str) -> None:
    info = osmo.wait_for(wf, ended, timeout=180)
    assert info["status"] == "COMPLETED", info
    use = next(t for t in info["tasks"] if t["name"] == "use")
    assert Path(use["output"], "seen").read_text() == EVERYTHING


def test_server_killed_while_promoting_on_its_host(osmo: Osmo, tmp_path: Path) -> None:
    osmo("server", "start", check=True)
    pid = osmo.server_pid()
    assert pid is not None
    wf = osmo.submit(write(tmp_path / "wf.yaml", SPEC))
    output = osmo.home / "runs" / wf / "make" / "0" / "output"
    _kill_when(pid, output.exists)  # renamed; being ingested
    _nothing_or_everything(output)
    _downstream_saw_everything(osmo, wf)  # (the next command restarts the server)


def test_server_killed_while_taking_in_a_remote_output(tmp_path: Path) -> None:
    cluster = Cluster(tmp_path)
    cluster.start_server()
    try:
        cluster.start_worker("w1", "--cpus", "1", host="elsewhere")  # blobs are sent
        pid = cluster.osmo.server_pid()
        assert pid is not None
        wf = cluster.osmo.submit(write(tmp_path / "wf.yaml", SPEC))
        attempt = cluster.osmo.home / "runs" / wf / "make" / "0"
        # the server builds the folder of links beside its final name, then renames it
        _kill_when(pid, lambda: attempt.is_dir() and any(
            n == "output" or n.startswith(".output.") for n in os.listdir(attempt)))
        _nothing_or_everything(attempt / "output")
        cluster.start_server()  # the worker registers again and reports the exit again
        _downstream_saw_everything(cluster.osmo, wf)
        assert cluster.osmo.query(wf)["tasks"][0]["retry"] == 0, "the finished task kept"
        _nothing_or_everything(attempt / "output")
    finally:
        cluster.stop()
