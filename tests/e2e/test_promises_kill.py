"""docs/reference/runtimes.md, Killing: "Cancel and timeouts kill the whole process group:
SIGTERM, then SIGKILL after 3 s."

The task and a child of it both ignore SIGTERM (recording when it arrived), so only the
SIGKILL that follows can end them, and the time it took is the grace.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from tests.conftest import Osmo, wait_gone, write

STUBBORN = """
import os, signal, sys, time
out = sys.argv[1]

def on_term(signum, frame):  # ignore SIGTERM, but say when it came
    with open(f"{out}/term-{os.getpid()}", "w") as f:
        f.write(repr(time.time()))

signal.signal(signal.SIGTERM, on_term)
os.fork()  # a child in the same process group, just as stubborn
with open(f"{out}/pids", "a") as f:
    f.write(f"{os.getpid()}\\n")
while True:
    time.sleep(0.05)
"""

GRACE = 3.0
# SIGKILL must follow within this long after SIGTERM arrived: the grace plus a margin for a
# loaded machine (reaping, this test's polling); a grace of 10 s, or none, fails.
MARGIN = 2.0


def test_cancel_sends_sigterm_then_sigkill_after_three_seconds(osmo: Osmo,
                                                               tmp_path: Path) -> None:
    spec = write(tmp_path / "wf.yaml", f"""
workflow:
  name: stubborn
  tasks:
  - name: t
    command: [python3, /opt/stubborn.py, "{tmp_path}"]
    files:
    - path: /opt/stubborn.py
      contents: |
{_indent(STUBBORN, 8)}
""")
    wf = osmo.submit(spec)
    deadline = time.monotonic() + 60
    while len(pids := _pids(tmp_path / "pids")) < 2:
        assert time.monotonic() < deadline, "the task never started"
        time.sleep(0.02)
    host = _host_pids(str(tmp_path), pids)  # in a sandbox the task's pids are its own
    canceled_at = time.time()
    osmo("cancel", wf, check=True)
    gone_at = {}
    for pid in pids:
        wait_gone(host[pid], timeout=GRACE + MARGIN + 10)
        gone_at[pid] = time.time()
    for pid in pids:
        assert gone_at[pid] - canceled_at >= GRACE, "SIGKILL came before the grace ran out"
        term = tmp_path / f"term-{pid}"
        assert term.exists(), "SIGTERM came first"
        term_at = float(term.read_text())
        assert canceled_at <= term_at
        assert gone_at[pid] - term_at <= GRACE + MARGIN, "SIGKILL came too late"
    info = osmo.wait_for(wf, lambda i: i["status"] == "FAILED_CANCELED")
    assert info["tasks"][0]["status"] == "FAILED_CANCELED"
    assert "still running 3s after SIGTERM: SIGKILL" in osmo("logs", wf, check=True).out


def _pids(path: Path) -> list[int]:
    try:
        return [int(p) for p in path.read_text().split()]
    except FileNotFoundError:
        return []


def _host_pids(marker: str, pids: list[int]) -> dict[int, int]:
    """The task's own pid → its pid on this host, for processes whose command line holds
    ``marker`` (``NSpid`` in ``/proc/<pid>/status``: its pid in each pid namespace)."""
    found = {}
    for name in os.listdir("/proc"):
        try:
            if not name.isdigit() or marker.encode() not in Path(
                    f"/proc/{name}/cmdline").read_bytes():
                continue
            status = Path(f"/proc/{name}/status").read_text()
        except OSError:
            continue
        nspid = [line.split()[-1] for line in status.splitlines() if line.startswith("NSpid:")]
        if nspid and int(nspid[0]) in pids:
            found[int(nspid[0])] = int(name)
    assert set(found) == set(pids), (found, pids)
    return found


def _indent(text: str, n: int) -> str:
    return "\n".join(" " * n + line if line else "" for line in text.strip("\n").splitlines())
