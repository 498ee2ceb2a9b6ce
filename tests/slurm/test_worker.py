"""``osmo worker --runtime slurm`` end to end: a server, a worker on the "login host" and
a real Slurm cluster (tests/slurm/cluster.py), driven through the real CLI.

OSMO's tutorials (tests/containers/osmo_tutorials, unmodified) run as Slurm batch jobs whose
agent runs each task in its image through podman on the compute node, with the offline
test images; their outputs, lineage and logs are checked as the container tests check
them. The cluster and the worker are the session's (tests/slurm/grid.py).
"""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from osmo.config import free_port
from osmo.runtime.container import ContainerEngine
from osmo.runtime.container.runtime import owner_id
from osmo.runtime.slurm import Slurm
from osmo.runtime.slurm.runtime import LIMIT_TTL
from tests.conftest import REPO, write
from tests.containers.submitting import (
    check_serial_tutorial,
    leftovers,
    lineage_of,
    osmo_lines,
    submitted_id,
    task_lines,
    tasks,
)
from tests.containers.test_tutorials import TUTORIALS
from tests.e2e.cluster import Cluster
from tests.slurm.cluster import SlurmCluster
from tests.slurm.grid import WORKER, jobs_of, logs, start_login, until_logged, until_no_job


def run(grid: Cluster, spec: Path, *, code: int = 0) -> tuple[str, dict[str, list[str]],
                                                              dict[str, dict]]:
    r = grid.osmo("submit", str(spec), "--wait", timeout=300)
    wf_id = submitted_id(r.out)
    lines, rows = task_lines(grid.osmo, wf_id), tasks(grid.osmo, wf_id)
    assert r.code == code, f"{r.out}{r.err}{lines}{rows}\n{grid.worker_log(WORKER)}"
    return wf_id, lines, rows


def test_the_worker_offers_its_partitions_capacity(grid: Cluster, roomy: SlurmCluster
                                                   ) -> None:
    assert not Slurm(roomy.env).has_pyxis()  # Debian's Slurm: image tasks go to podman
    node = grid.nodes()[WORKER]
    assert node["runtime"].startswith("slurm (slurm-wlm 22.05"), node
    assert "podman" in node["runtime"], node
    assert node["total"]["cpu"] == 4, node  # two nodes of 2 CPUs
    assert node["total"]["gpu"] == 2, node  # one fake GPU each
    assert node["total"]["memory"] == 2 * 2048 << 20, node


def test_a_drained_node_stops_counting_in_what_the_worker_offers(
        grid: Cluster, roomy: SlurmCluster) -> None:
    """A node drained for maintenance leaves the worker's offer within ``--capacity-every``,
    and comes back when it is resumed (before: a drained node's CPUs still counted)."""
    proc = grid.start_worker("login-drain", "--runtime", "slurm", "--capacity-every", "0.5",
                             pool="drain")

    def until(cpus: float) -> None:
        deadline = time.monotonic() + 30
        while (now := grid.nodes()["login-drain"]["total"]["cpu"]) != cpus:
            assert time.monotonic() < deadline, (now, grid.worker_log("login-drain"))
            time.sleep(0.2)

    try:
        until(4)
        roomy.run("scontrol", "update", "NodeName=n2", "State=DRAIN", "Reason=maintenance")
        try:
            until(2)
        finally:
            roomy.run("scontrol", "update", "NodeName=n2", "State=RESUME")
        until(4)
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(60) == 0, grid.worker_log("login-drain")


def test_hello_world(grid: Cluster, roomy: SlurmCluster, engine: ContainerEngine) -> None:
    wf_id, lines, rows = run(grid, TUTORIALS / "hello_world.yaml")
    assert lines["hello"] == ["Hello from OSMO!"]
    said = osmo_lines(grid.osmo, wf_id, "hello")
    assert any(re.fullmatch(r"Slurm job \d+ submitted", line) for line in said), said
    assert any(re.fullmatch(r"\[osmo:progress\] Slurm job \d+ RUNNING on n[12]", line)
               for line in said), said
    assert jobs_of(roomy) == []
    owner = {"osmo.owner": owner_id(grid.root / WORKER)}
    assert leftovers(engine, owner) == ([], [])


def test_serial_workflow_outputs_and_lineage(grid: Cluster) -> None:
    wf_id, lines, rows = run(grid, TUTORIALS / "serial_workflow.yaml")
    check_serial_tutorial(lines, rows)
    made = lineage_of(grid.osmo, f"{wf_id}:task3")
    assert made["task"] == "task3", made


def test_parallel_tasks(grid: Cluster) -> None:
    _, lines, _ = run(grid, TUTORIALS / "parallel_tasks.yaml")
    for name in ("task-a", "task-b", "task-c"):
        assert lines[name] == [f"Hello from {name}"]


def test_a_process_task_sees_its_job_and_its_secret_stays_out_of_slurm(
        grid: Cluster, roomy: SlurmCluster, tmp_path: Path) -> None:
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: plain
  tasks:
  - name: first
    command: [sh, -c, 'echo "job $SLURM_JOB_ID"; echo data > {{output}}/a.txt']
  - name: second
    command: [sh, -c, 'cat {{input:0}}/a.txt']
    inputs:
    - task: first
""")
    _, lines, rows = run(grid, spec)
    assert re.fullmatch(r"job \d+", lines["first"][0]), lines
    assert lines["second"] == ["data"]


def test_exec_reaches_the_running_job_and_cancel_sends_sigterm_through_scancel(
        grid: Cluster, roomy: SlurmCluster, tmp_path: Path) -> None:
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: held
  timeout: {exec_timeout: 61s}
  tasks:
  - name: held
    command: [sh, -c, 'trap "echo got-term; exit 143" TERM; echo up; while :; do sleep 0.2; done']
    environment: {GREETING: hola}
""")
    wf_id = grid.osmo.submit(spec, "--priority", "LOW")
    until_logged(grid, wf_id, "[held] up")
    r = grid.osmo("workflow", "exec", wf_id, "held", "--", "sh", "-c",
                  'echo "$GREETING $OSMO_TASK $SLURM_JOB_ID"; exit 7')
    assert r.code == 7, r.out + r.err
    greeting, task, job = r.out.split()
    assert (greeting, task) == ("hola", "held") and job.isdigit(), r.out
    shown = roomy.run("scontrol", "show", "job", job).stdout
    # exec_timeout 61 s: two whole minutes; LOW: twice the pool's nice step
    assert "TimeLimit=00:02:00" in shown and "Nice=200" in shown, shown
    grid.osmo("cancel", wf_id, check=True)
    info = grid.osmo.wait_for(wf_id, lambda i: i["status"] == "FAILED_CANCELED", timeout=60)
    assert "[held] got-term" in logs(grid, wf_id), info
    until_no_job(roomy, "osmo-held-")


def test_osmo_exec_timeout_cancels_the_job(grid: Cluster, roomy: SlurmCluster,
                                           tmp_path: Path) -> None:
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: timed
  timeout: {exec_timeout: 3s}
  tasks:
  - name: slow
    command: [sh, -c, 'echo up; exec sleep 600']
""")
    wf_id = grid.osmo.submit(spec)
    info = grid.osmo.wait_for(wf_id, lambda i: i["status"].startswith("FAILED"), timeout=90)
    assert info["status"] == "FAILED_EXEC_TIMEOUT", info
    until_no_job(roomy, "osmo-slow-")


def test_a_job_slurm_ends_at_its_time_limit_is_failed_exec_timeout(
        grid: Cluster, roomy: SlurmCluster, tmp_path: Path) -> None:
    """The one Slurm test that waits out its minute-granular TIMEOUT (60 to ~100 s: Slurm
    checks time limits about every 30 s): a job started while its
    partition allows one minute. Its exec_timeout (5 min) is over that limit: the job asks
    for the limit (more would keep it PENDING for ever), and Slurm ends it there."""
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: late
  timeout: {exec_timeout: 5m}
  tasks:
  - name: late
    command: [sh, -c, 'echo up; exec sleep 600']
""")
    roomy.run("scontrol", "update", "PartitionName=debug", "MaxTime=1")
    try:
        time.sleep(LIMIT_TTL + 0.5)  # the worker reads the partitions' limits again
        wf_id = grid.osmo.submit(spec)
        until_logged(grid, wf_id, "[late] up")
        started = time.monotonic()
    finally:
        roomy.run("scontrol", "update", "PartitionName=debug", "MaxTime=INFINITE")
    info = grid.osmo.wait_for(wf_id, lambda i: i["status"].startswith("FAILED"), timeout=240)
    print(f"\na job of a one-minute partition ended {time.monotonic() - started:.1f} s after "
          "its task started")
    rows = tasks(grid.osmo, wf_id)
    assert info["status"] == "FAILED_EXEC_TIMEOUT", (info, rows)
    assert rows["late"]["exit_code"] == 3002, rows  # ExitCode.EXEC_TIMEOUT
    said = osmo_lines(grid.osmo, wf_id, "late")
    assert any("TIMEOUT" in line for line in said), said
    job = next(m.group(1) for line in said
               if (m := re.fullmatch(r"Slurm job (\d+) submitted", line)))
    assert roomy.sacct(job)["State"] == "TIMEOUT", roomy.sacct(job)
    assert any(line.startswith("exec_timeout 300s is over the partitions' time limit: the "
                               "job asks for 1 min") for line in said), said
    until_no_job(roomy, "osmo-late-")


def test_a_task_over_its_memory_ends_out_of_memory_137_with_the_reason(
        grid: Cluster, tmp_path: Path) -> None:
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: hungry
  resources:
    default: {cpu: 1, memory: 60Mi}
  tasks:
  - name: hungry
    command: [python3, -c, 'import time; x = bytearray(400 << 20); time.sleep(30)']
""")
    wf_id, _, rows = run(grid, spec, code=1)
    assert rows["hungry"]["exit_code"] == 137, rows
    said = osmo_lines(grid.osmo, wf_id, "hungry")
    assert any("OUT_OF_MEMORY" in line for line in said), said


def test_a_pending_job_shows_its_reason_then_runs_when_the_nodes_free(
        grid: Cluster, roomy: SlurmCluster, tmp_path: Path) -> None:
    blockers = [roomy.sbatch("sleep 600", "--cpus-per-task=2", f"--nodelist={node}")
                for node in roomy.nodes]
    for job in blockers:
        roomy.wait_job(job, ["RUNNING"])
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: queued
  tasks:
  - name: queued
    command: [echo, ran]
""")
    wf_id = grid.osmo.submit(spec)
    try:
        seen = until_logged(grid, wf_id, "PENDING: Resources")
        assert "[queued] ran" not in seen
        row = tasks(grid.osmo, wf_id)["queued"]
        assert row["status"] == "RUNNING", row
        assert re.fullmatch(r"Slurm job \d+ PENDING: Resources \(the nodes it needs are "
                            r"busy\)", row["waiting"]["reason"]), row
        assert "PENDING: Resources" in grid.osmo("query", wf_id, check=True).out
    finally:
        for job in blockers:
            roomy.run("scancel", job)
    info = grid.osmo.wait_for(wf_id, lambda i: i["status"] == "COMPLETED", timeout=90)
    assert "[queued] ran" in logs(grid, wf_id), info
    assert info["tasks"][0].get("waiting") is None, info
    events = grid.osmo("events", wf_id, check=True).out
    assert len(re.findall(r"RUNNING +on \S+ +waiting: Slurm job \d+ PENDING: Resources",
                          events)) == 1, events  # once, however many polls saw it
    assert "waits no more" in events, events


def test_a_restarted_worker_adopts_its_job_which_runs_once_with_its_log_and_output_whole(
        grid: Cluster, roomy: SlurmCluster, tmp_path: Path) -> None:
    """kill -9 of the login host's node during a job, then a restart: the job is adopted,
    not run again (one job, the task's side effect once), its log is whole with no line
    twice (what was shipped before the kill is not sent again), its output is promoted."""
    runs, gate = tmp_path / "runs", tmp_path / "gate"
    spec = write(tmp_path / "wf.yaml", f"""
workflow:
  name: adopted
  tasks:
  - name: adopted
    command: [sh, -c, 'echo "$SLURM_JOB_ID" >> {runs}; echo up; echo "warm" >&2;
      while [ ! -e {gate} ]; do sleep 0.2; done; echo after; echo kept > {{{{output}}}}/r.txt']
""")
    wf_id = grid.osmo.submit(spec)
    until_logged(grid, wf_id, "[adopted] warm")
    first = runs.read_text().split()[0]
    grid.signal(WORKER, signal.SIGKILL)
    grid.workers[WORKER].wait(timeout=30)
    start_login(grid)
    gate.touch()
    info = grid.osmo.wait_for(wf_id, lambda i: i["status"] in ("COMPLETED", "FAILED"),
                              timeout=120)
    said = osmo_lines(grid.osmo, wf_id, "adopted")
    assert info["status"] == "COMPLETED", (info, said, grid.worker_log(WORKER))
    assert runs.read_text().split() == [first], "the task ran once"
    assert roomy.sacct(first)["State"] == "COMPLETED", roomy.sacct(first)
    row = tasks(grid.osmo, wf_id)["adopted"]
    assert row["retry"] == 0, row
    assert (Path(row["output"]) / "r.txt").read_text() == "kept\n"
    assert task_lines(grid.osmo, wf_id)["adopted"] == ["up", "warm", "after"]
    assert any("adopted by node login after its restart" in line for line in said), "\n".join(said)
    name = roomy.sacct(first)["JobName"]
    every = roomy.run("sacct", "-c", "-P", "-n", "-o", "JobID,JobName").stdout.splitlines()
    assert [line for line in every if line.endswith(f"|{name}")] == [f"{first}|{name}"], \
        every  # one job of that attempt, ever


def test_a_restarted_worker_adopts_a_group_s_job_whole(
        grid: Cluster, roomy: SlurmCluster, tmp_path: Path) -> None:
    """A gang (one heterogeneous job, a member on n1 and one on n2) survives a kill -9 of
    the node: both members are adopted, the job runs once, the group completes. (The lead
    ends last: a group's members are stopped when its lead finishes.)"""
    runs, gate = tmp_path / "runs", tmp_path / "gate"
    spec = write(tmp_path / "wf.yaml", f"""
workflow:
  name: gang-adopted
  resources:
    default: {{cpu: 2, memory: 100Mi}}
  groups:
  - name: pair
    tasks:
    - name: lead
      lead: true
      command: [sh, -c, 'echo "$SLURM_JOB_ID $SLURMD_NODENAME" >> {runs}; echo up;
        while [ ! -e {gate} ] || [ ! -e {runs}.peer ]; do sleep 0.2; done; echo lead done']
    - name: peer
      command: [sh, -c, 'echo "$SLURM_JOB_ID $SLURMD_NODENAME" >> {runs}; echo up;
        while [ ! -e {gate} ]; do sleep 0.2; done; echo peer done; touch {runs}.peer']
""")
    wf_id = grid.osmo.submit(spec)
    until_logged(grid, wf_id, "[lead] up")
    until_logged(grid, wf_id, "[peer] up")
    before = sorted(runs.read_text().splitlines())
    grid.signal(WORKER, signal.SIGKILL)
    grid.workers[WORKER].wait(timeout=30)
    start_login(grid)
    gate.touch()
    info = grid.osmo.wait_for(wf_id, lambda i: i["status"] in ("COMPLETED", "FAILED"),
                              timeout=120)
    lines = task_lines(grid.osmo, wf_id)
    assert info["status"] == "COMPLETED", (info, lines, grid.worker_log(WORKER))
    assert sorted(runs.read_text().splitlines()) == before, "each member ran once"
    assert {line.split()[1] for line in before} == {"n1", "n2"}, before
    assert lines == {"lead": ["up", "lead done"], "peer": ["up", "peer done"]}, lines
    assert all(row["retry"] == 0 for row in tasks(grid.osmo, wf_id).values())


def test_a_tampered_journal_entry_is_not_adopted_its_job_is_cancelled_and_rerun(
        grid: Cluster, roomy: SlurmCluster, tmp_path: Path) -> None:
    """Issue 29 item 6, hostile: the entry of the running attempt is rewritten while the
    node is down to name a folder outside its home. The restarted node drops it with a
    warning, cancels its job (never adopted through it) and the attempt runs again."""
    runs, gate = tmp_path / "runs", tmp_path / "gate"
    spec = gated_spec(tmp_path, "tampered", runs, gate)
    wf_id = grid.osmo.submit(spec)
    until_logged(grid, wf_id, "[tampered] up")
    first = runs.read_text().split()[0]
    grid.signal(WORKER, signal.SIGKILL)
    grid.workers[WORKER].wait(timeout=30)
    journal = grid.root / WORKER / "worker" / "journal"
    entries = list(journal.glob("attempt-*.json"))
    assert len(entries) == 1, entries
    assert oct(journal.stat().st_mode & 0o777) == "0o700"
    data = json.loads(entries[0].read_text())
    entries[0].write_text(json.dumps({**data, "task": "../../../../../tmp"}))
    start_login(grid)
    until_no_job(roomy, first)
    gate.touch()
    info = grid.osmo.wait_for(wf_id, lambda i: i["status"] in ("COMPLETED", "FAILED"),
                              timeout=120)
    assert info["status"] == "COMPLETED", (info, grid.worker_log(WORKER))
    ran = runs.read_text().split()
    assert len(ran) == 2 and ran[0] == first, ran
    assert roomy.sacct(first)["State"].startswith("CANCELLED"), roomy.sacct(first)
    assert "dropped the journal entry" in grid.worker_log(WORKER)


def test_a_node_away_past_the_grace_has_its_attempt_rescheduled_and_its_job_cancelled(
        roomy: SlurmCluster, podman_env: dict[str, str], tmp_path: Path) -> None:
    """Past ``--adopt-grace`` the node's attempt is lost and rescheduled; the node, back,
    is told it no longer holds it and cancels the job it left (no job outlives its
    attempt), then runs the new attempt."""
    runs, gate = tmp_path / "runs", tmp_path / "gate"
    c = Cluster(tmp_path / "c", server_args=("--adopt-grace", "2"),
                env={"SLURM_CONF": str(roomy.conf), "PATH": roomy.env["PATH"],
                     "CONTAINERS_CONF": podman_env["CONTAINERS_CONF"]})
    c.start_server()
    try:
        c.start_worker("late", "--runtime", "slurm")
        spec = gated_spec(tmp_path, "late", runs, gate)
        wf_id = c.osmo.submit(spec)
        until_logged(c, wf_id, "[late] up")
        first = runs.read_text().split()[0]
        c.signal("late", signal.SIGKILL)
        c.workers["late"].wait(timeout=30)
        c.osmo.wait_for(wf_id, lambda i: i["tasks"][0]["retry"] == 1, timeout=60)
        c.start_worker("late", "--runtime", "slurm")
        try:
            until_no_job(roomy, first, timeout=60)
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{c.worker_log('late')}\n"
                                 f"{(c.osmo.home / 'server.log').read_text()}") from None
        gate.touch()
        info = c.osmo.wait_for(wf_id, lambda i: i["status"] in ("COMPLETED", "FAILED"),
                               timeout=120)
        assert info["status"] == "COMPLETED", (info, c.worker_log("late"))
        ran = runs.read_text().split()
        assert len(ran) == 2 and ran[0] == first, ran
        gone = roomy.sacct(first)  # killed as a cancel kills: scancel's SIGTERM to the task
        assert gone["State"].startswith("CANCELLED") or gone["ExitCode"] == "143:0", gone
        assert "no longer placed on this node" in c.worker_log("late")
    finally:
        c.stop()  # kill -9: its jobs stay (they outlive it); cancelled here
        for line in jobs_of(roomy):
            if line.split()[-1].startswith("osmo-late-"):
                roomy.run("scancel", line.split()[0])


def test_group_communication_tutorial_runs_as_one_job(grid: Cluster) -> None:
    wf_id, lines, _ = run(grid, TUTORIALS / "group_tasks_communication.yaml")
    # {{host:server}} is the address of the node Slurm gave the server (both 127.0.0.1 here)
    assert lines["client"] == ["Client: Starting...", "Calling server at 127.0.0.1...",
                               "Received from server: hello", "Client: Complete"]
    assert lines["server"] == ["Server: Starting...", "Server: Complete"]
    said = osmo_lines(grid.osmo, wf_id, "client") + osmo_lines(grid.osmo, wf_id, "server")
    jobs = {m.group(1) for line in said
            if (m := re.fullmatch(r"Slurm job (\d+)\+[01] submitted .*", line))}
    assert len(jobs) == 1, said  # one heterogeneous job for the group


def test_combination_tutorial_leaves_no_container(grid: Cluster, engine: ContainerEngine
                                                  ) -> None:
    _, lines, rows = run(grid, TUTORIALS / "combination_workflow_simple.yaml")
    # a lead's end stops its peers: killed, their containers go too, even one being made
    assert leftovers(engine, {"osmo.owner": owner_id(grid.root / WORKER)}) == ([], [])
    samples = [f"sample_{i},value_{i}" for i in range(1, 11)]
    csv = Path(rows["generate-data"]["output"]) / "data" / "training_data.csv"
    assert csv.read_text().splitlines() == samples
    assert lines["train-model-a"] == ["Training Model A...", *samples, "✓ Model A complete!"]


GANG = """
workflow:
  name: gang
  timeout: {exec_timeout: 10m}
  resources:
    default: {cpu: 2, memory: 100Mi}
  groups:
  - name: pair
    tasks:
    - name: server
      lead: true
      command: [sh, -c, 'echo "server on $SLURMD_NODENAME"; echo hello | busybox nc -l -p PORT']
    - name: client
      command: [sh, -c, 'echo "client on $SLURMD_NODENAME";
        for i in $(seq 100); do busybox nc {{host:server}} PORT && exit 0; sleep 0.2; done;
        exit 1']
"""


def test_a_group_larger_than_the_cluster_fails_at_once_and_says_why(
        grid: Cluster, roomy: SlurmCluster, tmp_path: Path) -> None:
    """Slurm gives each component of a heterogeneous job a node of its own: a group of 3 on
    2 nodes would stay PENDING ("Resources") for ever. It fails, saying so."""
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: gang-of-three
  groups:
  - name: trio
    tasks:
    - name: a
      lead: true
      command: [sh, -c, "echo a"]
    - name: b
      command: [sh, -c, "echo b"]
    - name: c
      command: [sh, -c, "echo c"]
""")
    wf_id, _, rows = run(grid, spec, code=1)
    assert {name: row["status"] for name, row in rows.items()} == dict.fromkeys(
        "abc", "FAILED"), rows
    said = osmo_lines(grid.osmo, wf_id, "b")
    assert any("the pool's partitions have 2 nodes for its 3 members: it could never start"
               in line for line in said), said
    assert jobs_of(roomy) == []


def test_a_group_is_one_allocation_across_two_nodes_and_waits_whole_for_room(
        grid: Cluster, roomy: SlurmCluster, tmp_path: Path) -> None:
    blocker = roomy.sbatch("sleep 600", "--cpus-per-task=2", "--nodelist=n1")
    roomy.wait_job(blocker, ["RUNNING"])
    spec = write(tmp_path / "wf.yaml", GANG.replace("PORT", str(free_port(0))))
    wf_id = grid.osmo.submit(spec)
    try:
        seen = until_logged(grid, wf_id, "PENDING: Resources")
        assert " on n" not in seen  # neither member runs while the other cannot
        rows = grid.osmo.wait_for(wf_id, lambda i: all(
            t.get("waiting") for t in i["tasks"]), timeout=30)["tasks"]
        assert all(re.fullmatch(r"Slurm job \d+\+[01] PENDING: Resources \(.*\)",
                                t["waiting"]["reason"]) for t in rows), rows
        job = re.search(r"Slurm job (\d+)\+0 submitted", seen)
        assert job is not None, seen
        shown = roomy.run("scontrol", "show", "job", job.group(1)).stdout
        assert shown.count("TimeLimit=00:10:00") == 2, shown  # each component: --time
    finally:
        roomy.run("scancel", blocker)
    info = grid.osmo.wait_for(wf_id, lambda i: i["status"] in ("COMPLETED", "FAILED"),
                              timeout=90)
    lines = task_lines(grid.osmo, wf_id)
    assert info["status"] == "COMPLETED", (info, lines)
    assert lines["client"][-1] == "hello", lines
    nodes = {lines["server"][0].split()[-1], lines["client"][0].split()[-1]}
    assert nodes == {"n1", "n2"}, lines  # two CPUs each: one node each


@pytest.mark.parametrize("requeue", [True, False], ids=["requeued", "node_fail"])
def test_a_failed_node_s_job_runs_again_on_the_other_node_nothing_lost_or_doubled(
        grid: Cluster, roomy: SlurmCluster, tmp_path: Path, requeue: bool) -> None:
    """Slurm requeues a failed node's job by itself (the same job); a job it may not requeue
    ends NODE_FAIL, a lost attempt the node submits again. Neither is a retry."""
    runs, gate = tmp_path / "runs", tmp_path / "gate"
    spec = write(tmp_path / "wf.yaml", f"""
workflow:
  name: survivor
  tasks:
  - name: survivor
    command: [sh, -c, 'echo "$SLURMD_NODENAME" >> {runs}; echo line >> {{{{output}}}}/data.txt;
      echo "$SLURM_JOB_ID" > {runs}.job; echo up; while [ ! -e {gate} ]; do sleep 0.2; done']
""")
    wf_id = grid.osmo.submit(spec)
    until_logged(grid, wf_id, "[survivor] up")
    first = runs.read_text().split()[0]
    job = Path(f"{runs}.job").read_text().strip()
    if not requeue:
        roomy.run("scontrol", "update", f"JobId={job}", "Requeue=0")
    started = time.monotonic()
    roomy.kill_slurmd(first)
    try:
        gate.touch()
        info = grid.osmo.wait_for(wf_id, lambda i: i["status"] in ("COMPLETED", "FAILED"),
                                  timeout=150)
    finally:
        roomy.start_slurmd(first)
    print(f"a failed node's attempt completed {time.monotonic() - started:.1f}s after the kill")
    ran = runs.read_text().split()
    assert info["status"] == "COMPLETED", (info, logs(grid, wf_id))
    assert len(ran) == 2 and ran[0] == first and ran[1] != first, ran
    row = tasks(grid.osmo, wf_id)["survivor"]
    assert row["retry"] == 0, row  # Slurm's requeue: the same attempt, not a retry
    assert (Path(row["output"]) / "data.txt").read_text() == "line\n"  # the lost run's: gone
    if not requeue:
        assert roomy.sacct(job)["State"] == "NODE_FAIL", roomy.sacct(job)
        said = osmo_lines(grid.osmo, wf_id, "survivor")
        assert any(line.startswith(f"job {job}: Slurm: NODE_FAIL: the attempt is lost")
                   for line in said), said


def test_a_failed_node_s_gang_runs_again_whole_and_is_no_retry(
        grid: Cluster, roomy: SlurmCluster, tmp_path: Path) -> None:
    """A group's one heterogeneous job ends NODE_FAIL when a node of it fails (and it may not
    be requeued): each member's attempt is lost, not failed, and the group's job is submitted
    again, as a new attempt of each member that uses none of the workflow's retries."""
    runs, gate = tmp_path / "runs", tmp_path / "gate"
    member = ('[sh, -c, \'echo "{name} $SLURMD_NODENAME $SLURM_JOB_ID" >> ' + str(runs)
              + '; echo up; while [ ! -e ' + str(gate) + ' ]; do sleep 0.2; done\']')
    spec = write(tmp_path / "wf.yaml", f"""
workflow:
  name: gang-lost
  resources:
    default: {{cpu: 1, memory: 100Mi}}
  groups:
  - name: pair
    tasks:
    - name: lead
      lead: true
      command: {member.format(name="lead")}
    - name: peer
      command: {member.format(name="peer")}
""")
    wf_id = grid.osmo.submit(spec)
    until_logged(grid, wf_id, "[lead] up")
    until_logged(grid, wf_id, "[peer] up")
    first = {line.split()[0]: line.split()[1:] for line in runs.read_text().splitlines()}
    node, job = first["lead"]
    leader = job.split("+")[0]
    roomy.run("scontrol", "update", f"JobId={leader}", "Requeue=0")
    roomy.kill_slurmd(node)
    try:
        rows = grid.osmo.wait_for(wf_id, lambda i: i["status"] != "RUNNING" or all(
            t["retry"] == 1 and t["status"] == "RUNNING" for t in i["tasks"]), timeout=150)
    finally:
        roomy.start_slurmd(node)  # back: the new job may need it (or the other node)
    gate.touch()
    info = grid.osmo.wait_for(wf_id, lambda i: i["status"] in ("COMPLETED", "FAILED"),
                              timeout=120)
    assert info["status"] == "COMPLETED", (info, logs(grid, wf_id))
    again = [line.split() for line in runs.read_text().splitlines()[2:]]
    assert sorted(name for name, *_ in again) == ["lead", "peer"], again  # once each
    assert len({job.split("+")[0] for *_, job in again} - {leader}) == 1, again  # a new job
    assert [t["retry"] for t in rows["tasks"]] == [1, 1], rows
    said = osmo_lines(grid.osmo, wf_id, "lead")
    assert any("NODE_FAIL: the attempt is lost" in line for line in said), said
    events = grid.osmo("events", wf_id, "--format", "json", check=True).json()
    assert {e["message"] for e in events if e["status"] == "RESCHEDULED"} and all(
        "lost" in e["message"] or "NODE_FAIL" in e["message"]
        for e in events if e["status"] == "RESCHEDULED"), events


GUIDE = Path(__file__).parents[2] / "docs/tutorials/slurm.md"


def test_the_operator_guide_s_commands_start_a_worker_that_runs_tasks(
        grid: Cluster, tmp_path: Path) -> None:
    create, start = re.findall(r"```sh\n(.*?)```", GUIDE.read_text(), re.S)
    token = grid.osmo(*shlex.split(create)[1:], check=True).out.strip()
    argv = shlex.split(start.replace("\\\n", " "))
    assert argv[:2] == ["osmo", "worker"], argv
    given, rest = {}, []
    words = iter(argv[2:])
    for word in words:
        if word in ("--connect", "--name", "--pool"):
            given[word] = next(words)
        else:
            rest.append(word)
    name, pool = given["--name"] + "-guide", given["--pool"]
    grid.start_worker(name, *rest, pool=pool, token=token)
    try:
        assert grid.nodes()[name]["runtime"].startswith("slurm ("), grid.nodes()[name]
        spec = write(tmp_path / "wf.yaml", """
workflow:
  name: guide
  tasks:
  - name: hello
    command: [sh, -c, 'echo "hello from job $SLURM_JOB_ID"']
""")
        r = grid.osmo("submit", str(spec), "--pool", pool, "--wait", timeout=120)
        assert r.code == 0, r.out + r.err + grid.worker_log(name)
    finally:
        grid.signal(name, signal.SIGTERM)
        grid.workers[name].wait(timeout=60)


def test_a_login_host_without_slurm_s_commands_refuses_to_start_saying_which(
        grid: Cluster) -> None:
    env = dict(os.environ, OSMO_HOME=str(grid.root / "no-slurm"), PATH="/nonexistent",
               OSMO_TOKEN=grid.token("no-slurm"))
    done = subprocess.run([sys.executable, "-m", "osmo", "worker", "--connect", grid.endpoint,
                           "--name", "no-slurm", "--runtime", "slurm"], env=env, cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 3, done.stdout + done.stderr
    assert "sbatch not found on PATH" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr


def test_each_partition_is_a_platform_and_a_task_runs_in_its_own(
        grid: Cluster, roomy: SlurmCluster, tmp_path: Path) -> None:
    """A node that may use two partitions registers each as a platform with its capacity;
    a task with ``platform: P`` runs in partition P (on its node)."""
    parts = {"left": roomy.nodes[0], "right": roomy.nodes[1]}
    for part, node in parts.items():
        roomy.run("scontrol", "create", f"PartitionName={part}", f"Nodes={node}",
                  "MaxTime=INFINITE", "State=UP")
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: sides
  resources:
    left: {platform: left, cpu: 1}
    right: {platform: right, cpu: 1}
  tasks:
  - name: on-left
    resource: left
    command: [echo, left]
  - name: on-right
    resource: right
    command: [echo, right]
""")
    try:
        grid.start_worker("login-sides", "--runtime", "slurm", "--slurm-partition", "left",
                          "--slurm-partition", "right", pool="sides")
        node = grid.nodes()["login-sides"]
        assert {p: v["total"]["cpu"] for p, v in node["platforms"].items()} == {
            "left": 2, "right": 2}, node
        wf_id = grid.osmo.submit(spec, "--pool", "sides")
        info = grid.osmo.wait_for(wf_id, lambda i: i["status"] not in ("PENDING", "RUNNING"),
                                  timeout=120)
        assert info["status"] == "COMPLETED", info
        for task, part in (("on-left", "left"), ("on-right", "right")):
            said = osmo_lines(grid.osmo, wf_id, task)
            assert any(line.endswith(f"RUNNING on {parts[part]}") for line in said), said
    finally:
        if "login-sides" in grid.workers:
            grid.signal("login-sides", signal.SIGTERM)
            grid.workers["login-sides"].wait(timeout=60)
        for part in parts:
            roomy.run("scontrol", "delete", f"PartitionName={part}")


def gated_spec(tmp_path: Path, name: str, runs: Path, gate: Path) -> Path:
    """One task NAME that appends its Slurm job id to ``runs``, says up, and waits for ``gate``."""
    return write(tmp_path / "wf.yaml", f"""
workflow:
  name: {name}
  tasks:
  - name: {name}
    command: [sh, -c, 'echo "$SLURM_JOB_ID" >> {runs}; echo up;
      while [ ! -e {gate} ]; do sleep 0.2; done']
""")
