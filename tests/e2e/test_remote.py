"""Remote workers end to end: a server and workers as separate processes on loopback."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import (
    ended,
    process_alive,
    read_pid,
    unique_sleep,
    wait_gone,
    wait_no_process,
    write,
)
from tests.e2e.cluster import Cluster


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    c = Cluster(tmp_path, server_args=("--reconnect-grace", "20"),
                env={"OSMO_HOST_ID": "shared-host"})
    c.start_server()
    yield c
    c.stop()


def _task(info: dict, name: str) -> dict:
    return next(t for t in info["tasks"] if t["name"] == name)


def test_pools_and_platforms_place_tasks_on_the_right_workers(cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("cpu-1", "--cpus", "2", pool="cpu")
    cluster.start_worker("arm-1", "--cpus", "2", "--platform", "jetson", pool="edge")
    cluster.start_worker("x86-1", "--cpus", "2", "--platform", "x86", pool="edge")
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: placed
  resources:
    default: {cpu: 1}
  tasks:
  - name: on-cpu
    command: [sh, -c, "echo $OSMO_NODE > {{output}}/node"]
""")
    wf = cluster.osmo.submit(spec, "--pool", "cpu")
    info = cluster.osmo.wait_for(wf, ended)
    assert info["status"] == "COMPLETED", info
    assert _task(info, "on-cpu")["node"] == "cpu-1"
    assert "cpu-1" in cluster.osmo("query", wf, "-v", check=True).out  # the Node column
    # a resource whose platform no worker of the pool offers is a submit error
    r = cluster.osmo("submit", str(spec), "--pool", "nowhere")
    assert r.code != 0 and "nowhere" in (r.err + r.out)
    # the 'jetson' task only fits the jetson worker of pool 'edge'
    spec2 = write(tmp_path / "edge.yaml", """
workflow:
  name: edge
  resources:
    default: {cpu: 1, platform: jetson}
  tasks:
  - name: a
    command: [sh, -c, "echo $OSMO_NODE > {{output}}/node"]
  - name: b
    command: [sh, -c, "echo $OSMO_NODE > {{output}}/node"]
""")
    wf2 = cluster.osmo.submit(spec2, "--pool", "edge", "--no-cache")
    info2 = cluster.osmo.wait_for(wf2, ended)
    assert info2["status"] == "COMPLETED", info2
    for task in info2["tasks"]:
        assert task["node"] == "arm-1"
        assert Path(task["output"], "node").read_text().strip() == "arm-1"
    listed = cluster.osmo("pool", "list", "--format", "json", check=True).json()
    pools = {p["pool"]: p for p in listed}  # type: ignore[union-attr]
    assert pools["edge"]["nodes"] == 2 and pools["cpu"]["total"]["cpu"] == 2


def test_data_passes_between_workers_on_different_hosts(cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("a", "--platform", "pa", host="host-a")
    cluster.start_worker("b", "--platform", "pb", host="host-b")
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: across
  resources:
    default: {cpu: 1}
    pa: {cpu: 1, platform: pa}
    pb: {cpu: 1, platform: pb}
  tasks:
  - name: make
    resource: pa
    command: [sh, -c, "head -c 5000000 /dev/urandom > {{output}}/data.bin && mkdir {{output}}/sub && echo hi > {{output}}/sub/x.txt && echo $OSMO_NODE > {{output}}/node"]
  - name: use
    resource: pb
    command: [sh, -c, "sha256sum {{input:make}}/data.bin | cut -d' ' -f1 > {{output}}/sum && cat {{input:make}}/sub/x.txt > {{output}}/x && echo $OSMO_NODE > {{output}}/node"]
    inputs:
    - task: make
""")
    wf = cluster.osmo.submit(spec)
    info = cluster.osmo.wait_for(wf, ended)
    assert info["status"] == "COMPLETED", (info, cluster.worker_log("a"), cluster.worker_log("b"))
    make, use = _task(info, "make"), _task(info, "use")
    assert (make["node"], use["node"]) == ("a", "b")
    data = Path(make["output"], "data.bin").read_bytes()
    assert len(data) == 5_000_000
    assert Path(use["output"], "sum").read_text().strip() == hashlib.sha256(data).hexdigest()
    assert Path(use["output"], "x").read_text() == "hi\n"
    # worker b holds the bytes in its own store, not linked from the server's
    b_blob = tmp_path / "b" / "worker" / "artifacts" / "blobs" / "sha256"
    digest = hashlib.sha256(data).hexdigest()
    blob = b_blob / digest[:2] / digest[2:]
    assert blob.read_bytes() == data
    server_blob = tmp_path / "server" / "artifacts" / "blobs" / "sha256" / digest[:2] / digest[2:]
    assert blob.stat().st_ino != server_blob.stat().st_ino
    logs = cluster.osmo("logs", wf, check=True).out
    assert "[make][osmo] exit code 0" in logs and "[use][osmo] exit code 0" in logs


def test_same_host_worker_links_instead_of_copying(cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("w", pool="p", host="shared-host")
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: linked
  pool: p
  tasks:
  - name: make
    command: [sh, -c, "head -c 100000 /dev/urandom > {{output}}/d"]
  - name: use
    command: [sh, -c, "cmp {{input:make}}/d {{input:make}}/d && echo ok > {{output}}/ok"]
    inputs:
    - task: make
""")
    info = cluster.osmo.wait_for(cluster.osmo.submit(spec), ended)
    assert info["status"] == "COMPLETED", info
    digest = hashlib.sha256(Path(_task(info, "make")["output"], "d").read_bytes()).hexdigest()
    rel = Path("artifacts", "blobs", "sha256", digest[:2], digest[2:])
    worker_blob = tmp_path / "w" / "worker" / rel
    assert worker_blob.stat().st_ino == (tmp_path / "server" / rel).stat().st_ino


def _running_on(cluster: Cluster, wf: str, task: str) -> tuple[dict, str]:
    info = cluster.osmo.wait_for(wf, lambda i: _task(i, task)["status"] == "RUNNING")
    return info, _task(info, task)["node"]


# The README: a killed or cut-off worker "is noticed within about a second (the zenoh lease
# is 1 s)". Measured on a 2-core machine at load ~4, from the signal to the server's log line:
# SIGSTOP 0.76-0.99 s (6 runs), SIGKILL 2-6 ms (its TCP link closes at once). The margin
# covers a loaded CI machine (2.0 s failed now and then with the suite and other work at load
# 8+ on 2 cores); zenoh's default lease (10 s) still fails it.
NOTICED_WITHIN = 4.0

# One task that records its pid and start, then holds until the test releases the node it
# runs on (so nothing depends on how long a sleep lasts).
HELD = """
workflow:
  name: held
  tasks:
  - name: slow
    command: [sh, -c, "echo $$ > TMP/pid-$OSMO_NODE; echo $OSMO_NODE >> TMP/starts; while [ ! -e TMP/release-$OSMO_NODE ]; do sleep 0.05; done; echo $OSMO_NODE > {{output}}/node; touch TMP/done-$OSMO_NODE"]
"""


def _other(name: str) -> str:
    return "w2" if name == "w1" else "w1"


def _wait_file(path: Path, timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert time.monotonic() < deadline, f"{path} never appeared"
        time.sleep(0.02)


def _rerun_on(cluster: Cluster, wf: str, node: str) -> dict:
    info = cluster.osmo.wait_for(wf, lambda i: _task(i, "slow")["retry"] == 1
                                 and _task(i, "slow")["status"] == "RUNNING")
    assert _task(info, "slow")["node"] == node, info
    return info


def test_sigkill_of_a_worker_reschedules_its_task(cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("w1", "--cpus", "1")
    cluster.start_worker("w2", "--cpus", "1")
    wf = cluster.osmo.submit(write(tmp_path / "wf.yaml", HELD.replace("TMP", str(tmp_path))))
    _, victim = _running_on(cluster, wf, "slow")
    survivor = _other(victim)
    try:
        killed_at = time.time()
        cluster.signal(victim, signal.SIGKILL)
        noticed_at, _ = cluster.server_log_line(f"worker {victim} is gone")
        assert noticed_at - killed_at < NOTICED_WITHIN, "worker loss noticed too late"
        _rerun_on(cluster, wf, survivor)
        (tmp_path / f"release-{survivor}").touch()
        info = cluster.osmo.wait_for(wf, ended)
    finally:
        (tmp_path / f"release-{victim}").touch()  # the killed worker's task, if it lives on
    slow = _task(info, "slow")
    assert info["status"] == "COMPLETED" and slow["retry"] == 1
    assert Path(slow["output"], "node").read_text().strip() == survivor
    assert "RESCHEDULED" in cluster.osmo("logs", wf, check=True).out


def test_a_cut_off_worker_is_rescheduled_and_its_late_report_ignored(
        cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("w1", "--cpus", "1")
    cluster.start_worker("w2", "--cpus", "1")
    wf = cluster.osmo.submit(write(tmp_path / "wf.yaml", HELD.replace("TMP", str(tmp_path))))
    _, victim = _running_on(cluster, wf, "slow")
    survivor = _other(victim)
    stopped_at = time.time()
    cluster.signal(victim, signal.SIGSTOP)  # hung / network cut: only the lease notices
    noticed_at, _ = cluster.server_log_line(f"worker {victim} is gone")
    assert noticed_at - stopped_at < NOTICED_WITHIN, "a cut-off worker noticed too late"
    _rerun_on(cluster, wf, survivor)
    # The cut-off worker's attempt succeeds meanwhile (its task is not stopped), so the
    # worker holds a successful exit report with outputs for the superseded attempt 0.
    (tmp_path / f"release-{victim}").touch()
    _wait_file(tmp_path / f"done-{victim}")
    cluster.signal(victim, signal.SIGCONT)  # it wakes up and reports its stale attempt
    # refused: the attempt is no longer placed on that worker (the engine would fence it too),
    # whether the report comes with its registration or on its own just before it
    cluster.server_log_line(
        f"refused a finished report of worker {victim}: attempt '{wf}:slow:0' is not placed "
        "on it", f"refused 'worker_report' from {victim} (worker): attempt '{wf}:slow:0' is "
        f"not placed on worker {victim}")
    slow = _task(cluster.osmo.query(wf), "slow")
    assert (slow["status"], slow["retry"], slow["node"]) == ("RUNNING", 1, survivor), slow
    (tmp_path / f"release-{survivor}").touch()
    info = cluster.osmo.wait_for(wf, ended)
    slow = _task(info, "slow")
    assert info["status"] == "COMPLETED" and slow["retry"] == 1
    assert Path(slow["output"], "node").read_text().strip() == survivor
    lineage = cluster.osmo("lineage", f"{wf}:slow", "--format", "json", check=True).out
    assert f"{wf}:slow:1" in lineage and f"{wf}:slow:0" not in lineage


def test_server_restart_does_not_kill_running_tasks(cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("w1", "--cpus", "1")
    spec = write(tmp_path / "wf.yaml", HELD.replace("TMP", str(tmp_path)) + """
  - name: after
    command: [sh, -c, "cat {{input:slow}}/node > {{output}}/seen"]
    inputs:
    - task: slow
""")
    wf = cluster.osmo.submit(spec)
    _running_on(cluster, wf, "slow")
    task_pid = read_pid(tmp_path / "pid-w1")
    server_pid = cluster.osmo.server_pid()
    assert server_pid is not None
    os.kill(server_pid, signal.SIGKILL)
    wait_gone(server_pid)
    cluster.start_server()
    cluster.wait_online("w1")
    assert process_alive(task_pid), "the server's death must not stop the task"
    slow = _task(cluster.osmo.query(wf), "slow")
    assert (slow["status"], slow["retry"]) == ("RUNNING", 0), slow
    (tmp_path / "release-w1").touch()
    info = cluster.osmo.wait_for(wf, ended, timeout=60)
    assert info["status"] == "COMPLETED", (info, cluster.worker_log("w1"))
    assert _task(info, "slow")["retry"] == 0, "the running task must not have been rerun"
    assert (tmp_path / "starts").read_text() == "w1\n", "it started once"
    assert Path(_task(info, "after")["output"], "seen").read_text().strip() == "w1"


def test_sigterm_drains_a_worker(cluster: Cluster, tmp_path: Path) -> None:
    proc = cluster.start_worker("w1", "--cpus", "1", "--drain-timeout", "30")
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: drain
  tasks:
  - name: finishing
    command: [sh, -c, "sleep 2; head -c 200000 /dev/urandom > {{output}}/ckpt"]
  - name: queued
    command: [sh, -c, "echo $OSMO_NODE > {{output}}/node"]
""")
    wf = cluster.osmo.submit(spec)
    _running_on(cluster, wf, "finishing")
    cluster.signal("w1", signal.SIGTERM)
    assert proc.wait(timeout=40) == 0
    info = cluster.osmo.query(wf)
    done = _task(info, "finishing")
    assert done["status"] == "COMPLETED" and done["retry"] == 0
    assert Path(done["output"], "ckpt").stat().st_size == 200_000
    assert _task(info, "queued")["status"] != "COMPLETED"  # never taken by the draining worker
    cluster.start_worker("w2", "--cpus", "1")
    info = cluster.osmo.wait_for(wf, ended)
    assert info["status"] == "COMPLETED"
    assert Path(_task(info, "queued")["output"], "node").read_text().strip() == "w2"


def test_drain_timeout_hands_back_running_attempts(cluster: Cluster, tmp_path: Path) -> None:
    proc = cluster.start_worker("w1", "--cpus", "1", "--drain-timeout", "0.5")
    spec = write(tmp_path / "wf.yaml", f"""
workflow:
  name: handback
  tasks:
  - name: long
    command: [sh, -c, "echo $$ > {tmp_path}/pid; exec sleep 600"]
""")
    wf = cluster.osmo.submit(spec)
    _running_on(cluster, wf, "long")
    pid = read_pid(tmp_path / "pid")
    cluster.signal("w1", signal.SIGTERM)
    assert proc.wait(timeout=30) == 0
    wait_gone(pid, timeout=5)  # handed back means killed, not left running
    info = cluster.osmo.wait_for(wf, lambda i: _task(i, "long")["retry"] >= 1)
    assert _task(info, "long")["status"] in ("WAITING", "SCHEDULING", "PENDING")
    cluster.osmo("cancel", wf, check=True)


def test_worker_health_and_resource_list(cluster: Cluster) -> None:
    cluster.start_worker("w1", "--cpus", "1", "--memory", "2Gi", "--label", "zone=a")
    nodes = cluster.nodes()
    assert nodes["w1"]["total"]["cpu"] == 1 and nodes["w1"]["total"]["memory"] == 2 << 30
    assert nodes["w1"]["kind"] == "remote" and nodes["w1"]["status"] == "online"
    env = dict(cluster.osmo.env, OSMO_HOME=str(cluster.root / "w1"))
    import subprocess
    import sys

    ok = subprocess.run([sys.executable, "-m", "osmo", "health", "--worker"], env=env,
                        capture_output=True, text=True, timeout=30)
    assert ok.returncode == 0 and "w1" in ok.stdout
    r = cluster.osmo("--server", cluster.endpoint, "health")
    assert r.code == 0
    text = cluster.osmo("workers", check=True).out
    assert "w1" in text and "online" in text


def test_remote_client_with_server_flag_env_and_profile(cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("w1")
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: remote-client
  tasks:
  - name: t
    command: [echo, hi]
""")
    from tests.conftest import Osmo

    laptop = Osmo(tmp_path / "laptop")  # a different machine: no server of its own
    r = laptop("--server", cluster.endpoint, "list")  # no token: refused, exit 3
    assert r.code == 3 and "needs a token" in r.err and "Traceback" not in r.err
    token = cluster.token("laptop", "user")
    r = laptop("--server", cluster.endpoint, "--token", token, "submit", str(spec), "--wait")
    assert r.code == 0, r.err
    laptop.env.update(OSMO_SERVER=cluster.endpoint, OSMO_TOKEN=token)
    assert laptop("list", "--format", "json", check=True).json()[0]["name"] == "remote-client"  # type: ignore[index]
    del laptop.env["OSMO_SERVER"], laptop.env["OSMO_TOKEN"]
    laptop("profile", "set", "server", cluster.endpoint, check=True)
    laptop("profile", "set", "token", token, check=True)
    assert (laptop.home / "profile.json").stat().st_mode & 0o777 == 0o600
    assert "remote-client" in laptop("list", check=True).out
    assert laptop("query", r.out.splitlines()[0].split(" - ")[1], "--format", "json",
                  check=True).json()["submitted_by"] == "laptop"  # type: ignore[index]
    assert laptop.server_pid() is None  # nothing was started on the laptop
    unreachable = Osmo(tmp_path / "other")
    r = unreachable("--server", "tcp/127.0.0.1:9", "list")
    assert r.code == 3 and "Traceback" not in r.err and "cannot connect" in r.err
    json.dumps(r.err)


def test_tutorial_run_across_machines(tmp_path: Path) -> None:
    """The "Run across machines" block of docs/tutorials/remote-workers.md, on loopback with a
    free port."""
    import subprocess
    import sys

    from osmo.config import free_port
    from tests.conftest import REPO, Osmo
    from tests.docs.blocks import first_block, section

    block = first_block(section("docs/tutorials/remote-workers.md", "## Run across machines"),
                        "sh")
    port = str(free_port(0))
    server, laptop = Osmo(tmp_path / "server"), Osmo(tmp_path / "laptop")
    worker_env = dict(server.env, OSMO_HOME=str(tmp_path / "worker"))
    envs = {"server": server.env, "worker": worker_env, "laptop": laptop.env}
    where, worker_proc = "server", None
    try:
        for line in block.splitlines():  # each line as a shell runs it, in one folder
            if line.startswith("# on "):
                where = next((w for w in ("worker", "laptop") if w in line), "server")
                continue
            if not line.startswith("osmo "):
                continue
            line = line.split("  #")[0].strip().replace("0.0.0.0:7447", f"127.0.0.1:{port}")
            line = line.replace("SERVER:7447", f"127.0.0.1:{port}").replace(
                " workflows/", f" {REPO}/workflows/")
            cmd = ["bash", "-euo", "pipefail", "-c",
                   f'osmo() {{ exec "{sys.executable}" -m osmo "$@"; }}; {line}']
            if where == "worker":
                worker_proc = subprocess.Popen(cmd, env=worker_env, cwd=tmp_path,
                                               stdout=subprocess.DEVNULL,
                                               stderr=subprocess.DEVNULL)
                deadline = time.monotonic() + 30
                while "gpu-1" not in server("workers").out:
                    assert time.monotonic() < deadline, "the tutorial's worker never came online"
                    time.sleep(0.1)
                continue
            r = subprocess.run(cmd, env=envs[where], cwd=tmp_path, capture_output=True,
                               text=True, timeout=180)
            assert r.returncode == 0, (line, r.stdout, r.stderr)
            if " workers" in line:
                assert "gpu-1" in r.stdout and "x86-l4" in r.stdout and "online" in r.stdout
            if " submit" in line:
                assert "COMPLETED" in r.stdout
        assert laptop.server_pid() is None
        assert (tmp_path / "gpu-1.token").stat().st_size > 0
    finally:
        if worker_proc is not None:
            worker_proc.kill()  # bash exec'd the worker: this pid is the worker
            worker_proc.wait()
        server.stop_server()


def test_remote_client_moves_files_both_ways(cluster: Cluster, tmp_path: Path) -> None:
    """artifacts get, dataset upload and download from a machine that is not the server's."""
    from tests.conftest import Osmo

    cluster.start_worker("w1", host="worker-host")
    laptop = Osmo(tmp_path / "laptop")
    laptop.env.update(OSMO_SERVER=cluster.endpoint, OSMO_HOST_ID="laptop-host",
                      OSMO_TOKEN=cluster.token("laptop", "user"))
    data = tmp_path / "mine"
    (data / "sub").mkdir(parents=True)
    (data / "a.bin").write_bytes(bytes(range(256)) * 4000)
    (data / "sub" / "b.txt").write_text("bee\n")
    r = laptop("dataset", "upload", "demos", str(data), check=True)
    assert "1" in r.out
    assert (data / "a.bin").stat().st_mode & 0o200, "the user's own files stay writable"
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: uses-dataset
  tasks:
  - name: t
    inputs:
    - dataset: {name: demos}
    command: [sh, -c, "cat {{input:0}}/sub/b.txt > {{output}}/b && cp {{input:0}}/a.bin {{output}}/a.bin"]
""")
    r = laptop("submit", str(spec), "--wait")
    assert r.code == 0, r.out + r.err
    wf = r.out.splitlines()[0].split(" - ")[1].strip()
    out = tmp_path / "got"
    laptop("artifacts", "get", f"{wf}:t", "-o", str(out), check=True)
    assert (out / "b").read_text() == "bee\n"
    assert (out / "a.bin").read_bytes() == (data / "a.bin").read_bytes()
    back = tmp_path / "back"
    laptop("dataset", "download", "demos", "-o", str(back), check=True)
    assert (back / "sub" / "b.txt").read_text() == "bee\n"
    assert not (tmp_path / "server" / "got").exists() and not Path("/got").exists()


def test_cancel_and_timeout_reach_remote_tasks(cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("w1", "--cpus", "2", host="elsewhere")
    pidfile = tmp_path / "pid"
    spec = write(tmp_path / "wf.yaml", f"""
workflow:
  name: stopme
  tasks:
  - name: long
    command: [sh, -c, "echo started; sleep 600 & echo $! > {pidfile}; wait"]
""")
    wf = cluster.osmo.submit(spec)
    child = read_pid(pidfile)
    cluster.osmo("cancel", wf, check=True)
    info = cluster.osmo.wait_for(wf, ended)
    assert info["status"] == "FAILED_CANCELED"
    wait_gone(child, timeout=10)  # the remote task's whole process group was killed
    logs = cluster.osmo("logs", wf, check=True).out
    assert "[long] started" in logs  # streamed from the worker
    marker = unique_sleep()
    timed = write(tmp_path / "timeout.yaml", f"""
workflow:
  name: timed
  timeout: {{exec_timeout: 2s}}
  tasks:
  - name: slow
    command: [sh, -c, "echo $$ > {tmp_path}/timed-pid; exec sleep {marker}"]
""")
    info = cluster.osmo.wait_for(cluster.osmo.submit(timed), ended, timeout=60)
    assert info["status"] == "FAILED_EXEC_TIMEOUT", info
    assert (tmp_path / "timed-pid").exists()  # it ran
    wait_no_process(marker, timeout=10)  # the worker killed it
