"""End to end through the real CLI and a real server: DAGs, data, groups, retries, timeouts."""

from __future__ import annotations

import shutil
import socket
from pathlib import Path

from tests.conftest import REPO, Osmo, unique_sleep, wait_no_process, write


def _statuses(info: dict) -> dict[str, str]:
    return {t["name"]: t["status"] for t in info["tasks"]}


def test_demo_pipeline_runs_and_logs_show_every_task(shared_osmo: Osmo) -> None:
    r = shared_osmo("submit", str(REPO / "workflows/hello-pipeline.yaml"), "--wait")
    assert r.code == 0, r.err + r.out
    wf_id = r.out.splitlines()[0].split(" - ")[1]
    assert wf_id.startswith("hello-pipeline-")
    info = shared_osmo.query(wf_id)
    assert info["status"] == "COMPLETED"
    assert set(_statuses(info).values()) == {"COMPLETED"}
    logs = shared_osmo("logs", wf_id, check=True).out
    assert "[generate] wrote 20 samples to samples.csv" in logs
    assert "[square] squared 20 samples" in logs
    assert "[absolute] took absolute values of 20 samples" in logs
    assert "[report] samples=20 mean_square=" in logs
    report = Path(info["tasks"][-1]["output"]) / "report.txt"
    assert report.read_text().startswith("samples=20 ")


def test_set_overrides_default_values(shared_osmo: Osmo) -> None:
    r = shared_osmo("submit", str(REPO / "workflows/hello-pipeline.yaml"), "--set", "samples=5",
                    "--wait")
    assert r.code == 0, r.err
    wf_id = r.out.splitlines()[0].split(" - ")[1]
    assert "[report] samples=5 " in shared_osmo("logs", wf_id, "-t", "report").out


def test_parallel_tasks_run_at_the_same_time(shared_osmo: Osmo, tmp_path: Path) -> None:
    # Each task waits for the other's marker: they can only finish if both run at once.
    spec = write(tmp_path / "par.yaml", f"""
workflow:
  name: par
  timeout: {{exec_timeout: 60s}}
  tasks:
  - name: left
    command: [sh, -c, "touch {tmp_path}/left; while [ ! -e {tmp_path}/right ]; do sleep 0.05; done"]
  - name: right
    command: [sh, -c, "touch {tmp_path}/right; while [ ! -e {tmp_path}/left ]; do sleep 0.05; done"]
""")
    r = shared_osmo("submit", str(spec), "--wait")
    assert r.code == 0, r.out + r.err


def test_files_are_private_per_attempt(shared_osmo: Osmo, tmp_path: Path) -> None:
    tasks = "".join(f"""
  - name: t{i}
    command: [sh, /tmp/run.sh]
    files:
    - path: /tmp/run.sh
      contents: "sleep 0.3; cat /tmp/run.sh > {{{{output}}}}/seen.txt; echo mine-{i}"
""" for i in range(2))
    spec = write(tmp_path / "files.yaml", f"workflow:\n  name: files\n  tasks:{tasks}")
    r = shared_osmo("submit", str(spec), "--wait")
    assert r.code == 0, r.out + r.err
    info = shared_osmo.query(r.out.splitlines()[0].split(" - ")[1])
    for i, task in enumerate(info["tasks"]):
        seen = (Path(task["output"]) / "seen.txt").read_text()
        assert f"echo mine-{i}" in seen and f"mine-{1 - i}" not in seen
    assert not Path("/tmp/run.sh").exists() or "mine-" not in Path("/tmp/run.sh").read_text()


def test_group_lead_and_host_networking(shared_osmo: Osmo, tmp_path: Path) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    spec = write(tmp_path / "group.yaml", """
workflow:
  name: netgroup
  timeout: {exec_timeout: 90s}
  groups:
  - name: sim
    tasks:
    - name: server
      command: [python3, -m, http.server, "{{port}}", --bind, "{{host:server}}"]
    - name: client
      lead: true
      command: [python3, /tmp/client.py, "{{host:server}}", "{{port}}", "{{output}}"]
      files:
      - path: /tmp/client.py
        contents: |
          import sys, time, urllib.request
          host, port, out = sys.argv[1:4]
          for _ in range(300):
              try:
                  body = urllib.request.urlopen(f"http://{host}:{port}/", timeout=2).read()
                  break
              except OSError:
                  time.sleep(0.1)
          open(out + "/page.html", "wb").write(body)
          print("fetched", len(body), "bytes from", host)
""")
    r = shared_osmo("submit", str(spec), "--set", f"port={port}", "--wait")
    assert r.code == 0, r.out + r.err
    wf_id = r.out.splitlines()[0].split(" - ")[1]
    info = shared_osmo.query(wf_id)
    status = _statuses(info)
    assert status["client"] == "COMPLETED"
    assert status["server"] == "COMPLETED"  # stopped once the lead finished
    server = [t for t in info["tasks"] if t["name"] == "server"][0]
    assert "lead finished" in server["message"]
    assert "fetched" in shared_osmo("logs", wf_id, "-t", "client").out


BARRIER = """
workflow:
  name: barrier
  timeout: {exec_timeout: 120s}
  groups:
  - name: gang
    tasks:
    - name: slow
      command: [sh, -c, "date +%s.%N > TMP/start-slow"]
      inputs:
      - url: file://TMP/big
    - name: lead
      lead: true
      command: [sh, -c, "date +%s.%N > TMP/start-lead; i=0; while [ ! -e TMP/start-slow ]; do i=$((i+1)); [ $i -lt 1200 ] || exit 9; sleep 0.05; done"]
"""


def test_group_barrier_holds_every_command_until_all_are_prepared(shared_osmo: Osmo,
                                                                  tmp_path: Path) -> None:
    """No member's command starts before the whole group is prepared. ``slow``'s
    preparation downloads and verifies 256 MiB, ``lead``'s takes milliseconds: without the
    barrier ``lead`` starts long before ``slow`` is prepared (seen: 1.2-1.35 s early with
    the pool starting attempts at prepare; 0.5-0.6 s with 128 MiB and the scheduler
    releasing the barrier at the first prepared member)."""
    (tmp_path / "big").mkdir()
    with open(tmp_path / "big" / "data.bin", "wb") as f:
        f.truncate(256 << 20)  # sparse: costs no disk here
    r = shared_osmo("submit", str(write(tmp_path / "b.yaml",
                                        BARRIER.replace("TMP", str(tmp_path)))), "--wait")
    assert r.code == 0, r.out + r.err
    wf = r.out.splitlines()[0].split(" - ")[1]
    assert _statuses(shared_osmo.query(wf)) == {"slow": "COMPLETED", "lead": "COMPLETED"}
    # slow's input landed at the end of its preparation (the download is its slow part)
    landed = shared_osmo.home / "runs" / wf / "slow" / "0.inputs" / "0" / "data.bin"
    prepared = landed.stat().st_mtime
    starts = {n: float((tmp_path / f"start-{n}").read_text()) for n in ("slow", "lead")}
    shutil.rmtree(landed.parent.parent)  # the 256 MiB copy
    early = {n: round(prepared - t, 3) for n, t in starts.items() if t < prepared}
    assert not early, f"started before the group was prepared (seconds early): {early}"


def test_exit_action_reschedules_until_success(shared_osmo: Osmo, tmp_path: Path) -> None:
    counter = tmp_path / "count"
    spec = write(tmp_path / "retry.yaml", f"""
workflow:
  name: flaky
  tasks:
  - name: flaky
    command: [sh, -c, "echo x >> {counter}; n=$(wc -l < {counter}); echo try $n; [ $n -ge 3 ] || exit 42"]
    exitActions:
      RESCHEDULE: 42
""")
    r = shared_osmo("submit", str(spec), "--wait")
    assert r.code == 0, r.out + r.err
    wf_id = r.out.splitlines()[0].split(" - ")[1]
    task = shared_osmo.query(wf_id)["tasks"][0]
    assert task["retry"] == 2 and task["status"] == "COMPLETED"
    logs = shared_osmo("logs", wf_id).out
    assert "[flaky] try 1" in logs and "[flaky retry-1] try 2" in logs
    assert "[flaky retry-2] try 3" in logs
    assert "[flaky][osmo] RESCHEDULED" in logs
    only_retry_1 = shared_osmo("logs", wf_id, "-r", "1").out
    assert "try 2" in only_retry_1 and "try 3" not in only_retry_1


def test_retry_cap_from_workflow(shared_osmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "cap.yaml", """
workflow:
  name: capped
  maxRetries: 1
  tasks:
  - name: always
    command: [sh, -c, "exit 7"]
    exitActions: {RESCHEDULE: "1-10"}
""")
    r = shared_osmo("submit", str(spec), "--wait")
    assert r.code == 1
    task = shared_osmo.query(r.out.splitlines()[0].split(" - ")[1])["tasks"][0]
    assert task["status"] == "FAILED" and task["retry"] == 1 and task["exit_code"] == 7


def test_exec_timeout_kills_and_fails(shared_osmo: Osmo, tmp_path: Path) -> None:
    marker = unique_sleep()
    spec = write(tmp_path / "slow.yaml", f"""
workflow:
  name: slow
  timeout: {{exec_timeout: 1s}}
  tasks:
  - name: sleeper
    command: [sh, -c, "echo $$ > {tmp_path}/pid; exec sleep {marker}"]
  - name: after
    command: ["true"]
    inputs: [{{task: sleeper}}]
""")
    r = shared_osmo("submit", str(spec), "--wait")
    assert r.code == 1
    info = shared_osmo.query(r.out.splitlines()[0].split(" - ")[1])
    assert info["status"] == "FAILED_EXEC_TIMEOUT"
    assert _statuses(info) == {"sleeper": "FAILED_EXEC_TIMEOUT", "after": "FAILED_UPSTREAM"}
    assert (tmp_path / "pid").exists()  # it ran
    wait_no_process(marker, timeout=10)  # killed, not just marked


def test_upstream_failure_cascades(shared_osmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "cascade.yaml", """
workflow:
  name: cascade
  tasks:
  - {name: a, command: [sh, -c, "echo partial > {{output}}/x; exit 3"]}
  - {name: b, command: ["true"], inputs: [{task: a}]}
  - {name: c, command: ["true"], inputs: [{task: b}]}
  - {name: side, command: ["true"]}
""")
    r = shared_osmo("submit", str(spec), "--wait")
    assert r.code == 1
    info = shared_osmo.query(r.out.splitlines()[0].split(" - ")[1])
    assert info["status"] == "FAILED"
    assert _statuses(info) == {"a": "FAILED", "b": "FAILED_UPSTREAM", "c": "FAILED_UPSTREAM",
                               "side": "COMPLETED"}
    by_name = {t["name"]: t for t in info["tasks"]}
    assert by_name["a"]["exit_code"] == 3 and by_name["a"]["output"] is None
    assert by_name["b"]["exit_code"] == 3000


def test_invalid_spec_is_rejected_with_positions_and_creates_nothing(shared_osmo: Osmo,
                                                                     tmp_path: Path) -> None:
    before = shared_osmo("list", "--format", "json", check=True).json()
    spec = write(tmp_path / "bad.yaml", """workflow:
  name: bad
  tasks:
  - name: a
    comand: [echo]
  - name: b
    command: [echo]
    inputs: [{task: c}]
""")
    r = shared_osmo("submit", str(spec))
    assert r.code == 2
    assert f"{spec}:5:5: unknown key 'comand'" in r.err and "did you mean 'command'" in r.err
    assert f"{spec}:8:" in r.err
    assert "Traceback" not in r.err
    assert shared_osmo("list", "--format", "json", check=True).json() == before


def test_task_that_can_never_fit_is_rejected_at_submit(shared_osmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "huge.yaml", """
workflow:
  name: huge
  resources:
    default: {cpu: 4096}
  tasks:
  - {name: big, command: ["true"]}
""")
    r = shared_osmo("submit", str(spec))
    assert r.code == 2, r.out + r.err
    assert "big" in r.err and "cpu" in r.err


def test_validate_and_dry_run(shared_osmo: Osmo) -> None:
    spec = str(REPO / "workflows/hello-pipeline.yaml")
    r = shared_osmo("validate", spec, check=True)
    assert "valid workflow 'hello-pipeline' with 4 task(s)" in r.out
    r = shared_osmo("submit", spec, "--dry-run", "--set", "samples=3", check=True)
    assert '"3"' in r.out or " 3" in r.out
    assert "{{output}}" in r.out


def test_workflow_verbs_and_json(shared_osmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "one.yaml", "workflow:\n  name: one\n  tasks:\n"
                 "  - {name: hi, command: [echo, hello]}\n")
    r = shared_osmo("workflow", "submit", str(spec), "--wait")
    assert r.code == 0
    wf_id = r.out.splitlines()[0].split(" - ")[1]
    listed = shared_osmo("workflow", "list", "--status", "completed", "--format", "json",
                         check=True).json()
    assert wf_id in [w["id"] for w in listed]
    last = shared_osmo("workflow", "logs", wf_id, "-n", "6").out.splitlines()
    assert len(last) == 6 and any("hello" in line for line in last)  # hello may precede RUNNING
    assert "name: one" in shared_osmo("workflow", "spec", wf_id, check=True).out
    text = shared_osmo("status", wf_id, check=True).out
    assert "COMPLETED" in text and "hi" in text
    assert shared_osmo("query", "nope-1").code == 2


def test_logs_follow_streams_until_the_workflow_ends(shared_osmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "follow.yaml", """
workflow:
  name: follow
  tasks:
  - name: talk
    command: [sh, -c, "for i in 1 2 3; do echo line $i; sleep 0.2; done; echo oops >&2"]
""")
    r = shared_osmo("submit", str(spec), "--format", "json", check=True)
    wf_id = r.json()["workflow_id"]  # type: ignore[index]
    followed = shared_osmo("logs", wf_id, "-f", timeout=120)
    assert followed.code == 0
    lines = [ln for ln in followed.out.splitlines() if "[talk] " in ln]
    assert [ln.split("[talk] ")[1] for ln in lines] == ["line 1", "line 2", "line 3", "oops"]
    assert "[workflow][osmo] COMPLETED" in followed.out
