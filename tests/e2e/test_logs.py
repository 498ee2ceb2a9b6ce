"""``osmo logs`` in chunks, end to end: several loud tasks merged in time order across many
requests, ``--tail`` and ``--since`` over all of them, ``--follow`` from a tail, and a reader
that stops reading."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import osmo
from tests.conftest import REPO, Osmo, write
from tests.hostile.datarun import finished

LINES = 100_000  # about 3 MB of records per task: many chunks


def test_loud_tasks_stream_merged_in_time_order(shared_osmo: Osmo, tmp_path: Path) -> None:
    wf = finished(shared_osmo, write(tmp_path / "two.yaml", f"""
workflow:
  name: two-loud
  tasks:
  - {{name: a, command: [seq, 1, "{LINES}"]}}
  - {{name: b, command: [seq, 1, "{LINES}"]}}
"""))
    with osmo.Client(home=shared_osmo.home) as client:
        every = list(client.iter_logs(wf, stream="stdout"))
        assert [r.ts for r in every] == sorted(r.ts for r in every)
        for task in "ab":
            assert [r.text for r in every if r.task == task] == [
                str(n) for n in range(1, LINES + 1)]
        tail = client.logs(wf, tail=5, stream="stdout")
        assert len(tail) == 5 and all(r in every for r in tail)
        assert [r for r in every if r.ts > tail[0].ts] == [r for r in tail
                                                           if r.ts > tail[0].ts]
        middle = every[len(every) // 2].ts
        since = client.logs(wf, since=middle, stream="stdout")
        assert since == [r for r in every if r.ts >= middle]
        whole = client.logs(wf)  # status lines too, in their place
        assert [r.ts for r in whole] == sorted(r.ts for r in whole)
        assert whole[-1].stream == "osmo" and whole[-1].text == "COMPLETED"
    head = subprocess.Popen([sys.executable, "-m", "osmo", "logs", wf], env=shared_osmo.env,
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert head.stdout is not None and head.stdout.readline()
    head.stdout.close()  # as `osmo logs ID | head -1` does
    _, err = head.communicate(timeout=120)
    assert head.returncode == 0 and err == b"", err[-2000:]


def test_follow_from_a_tail(shared_osmo: Osmo, tmp_path: Path) -> None:
    gate = tmp_path / "gate"
    spec = write(tmp_path / "talk.yaml", f"""
workflow:
  name: talk
  tasks:
  - name: talk
    command: [sh, -c, "echo one; echo two; while [ ! -f {gate} ]; do sleep 0.1; done; echo three"]
""")
    wf = shared_osmo.submit(spec)
    deadline = time.monotonic() + 60
    log = ""
    # the task's "two" and osmo's RUNNING (which a busy server may write after the task's
    # first lines): then nothing more is written until the gate opens
    while "[talk] two" not in log or "[talk][osmo] RUNNING" not in log:
        assert time.monotonic() < deadline, f"the task never printed:\n{log}"
        time.sleep(0.1)
        log = shared_osmo("logs", wf, "-t", "talk").out
    last = log.rstrip("\n").splitlines()[-1]
    follow = subprocess.Popen([sys.executable, "-m", "osmo", "logs", wf, "-t", "talk", "-f",
                               "--tail", "1"], env=shared_osmo.env, cwd=REPO,
                              stdout=subprocess.PIPE, text=True)
    assert follow.stdout is not None
    first = follow.stdout.readline()  # the tail, before the task goes on
    gate.touch()
    rest, _ = follow.communicate(timeout=120)
    assert follow.returncode == 0
    assert first.rstrip("\n") == last  # the tail is the log's last line, and only that
    lines = [line.split("[talk] ")[1] for line in rest.splitlines() if "[talk] " in line]
    assert lines == ["three"]
    assert "[talk][osmo] COMPLETED" in rest
