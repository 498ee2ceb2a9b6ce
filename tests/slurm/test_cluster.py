"""The test cluster itself (tests/slurm/cluster.py): what Slurm does here, for real.

These prove the harness the Slurm executor's tests will stand on: both nodes up on loopback,
batch jobs on a chosen node with their exit codes, a two-node allocation, scancel, memory and
time limits, fake GPUs, a node that fails under its jobs, and a stop that leaves nothing.
Timings (node failure, TIMEOUT) are printed (``pytest -s``) and kept in tests/slurm/README.md.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.slurm.cluster import SlurmCluster
from tests.slurm.conftest import require_slurm

ENDED = ("COMPLETED", "FAILED", "CANCELLED", "TIMEOUT", "OUT_OF_MEMORY", "NODE_FAIL")


def listening(port: int) -> set[str]:
    """The local addresses (hex, as /proc/net/tcp writes them) that listen on ``port``."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            local, state = line.split()[1], line.split()[3]
            address, _, hex_port = local.partition(":")
            if state == "0A" and int(hex_port, 16) == port:
                found.add(address)
    return found


def wait_until(condition: Callable[[], bool], timeout: float = 30) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "condition never held"
        time.sleep(0.1)


def test_both_nodes_are_idle_and_every_daemon_listens_on_loopback_only(
        slurm: SlurmCluster) -> None:
    assert slurm.node_states() == {"n1": "idle", "n2": "idle"}
    node = slurm.run("scontrol", "show", "node", "n1", "--oneliner").stdout
    assert "CPUTot=2" in node and "RealMemory=500" in node and "Gres=gpu:1" in node
    for port in (slurm.ctld_port, *slurm.node_ports.values()):
        assert listening(port) == {"0100007F"}, (port, listening(port))  # 127.0.0.1


@pytest.mark.parametrize("node", ["n1", "n2"])
def test_sbatch_wait_runs_the_script_on_the_node_asked_for_and_returns_its_exit_code(
        slurm: SlurmCluster, node: str) -> None:
    script = slurm.jobs / f"exit-on-{node}.sh"
    script.write_text("#!/bin/sh\necho \"on $SLURMD_NODENAME\"\nexit 7\n")
    done = slurm.run("sbatch", "--parsable", "--wait", f"--nodelist={node}",
                     f"--output={slurm.jobs}/%j.out", str(script), check=False, timeout=120)
    assert done.returncode == 7, done
    job_id = done.stdout.strip()
    assert slurm.output(job_id) == f"on {node}\n"
    record = slurm.sacct(job_id)
    assert (record["State"], record["ExitCode"], record["NodeList"]) == ("FAILED", "7:0", node)


def test_a_two_node_allocation_runs_its_steps_on_both_nodes(slurm: SlurmCluster) -> None:
    done = slurm.run("sbatch", "--parsable", "--wait", "--nodes=2", "--ntasks-per-node=1",
                     f"--output={slurm.jobs}/%j.out",
                     "--wrap", "srun printenv SLURMD_NODENAME", check=False, timeout=120)
    assert done.returncode == 0, done
    job_id = done.stdout.strip()
    assert sorted(slurm.output(job_id).split()) == ["n1", "n2"]
    assert slurm.sacct(job_id)["NodeList"] == "n[1-2]"


def test_scancel_ends_a_running_job_and_its_processes(slurm: SlurmCluster) -> None:
    job_id = slurm.sbatch("echo started; exec sleep 300")
    slurm.wait_job(job_id, ["RUNNING"])
    wait_until(lambda: any("sleep 300" in cmd for _, cmd in slurm.leftovers(daemons=False)))  # it runs
    slurm.run("scancel", job_id)
    assert slurm.wait_job(job_id, ENDED)["JobState"] == "CANCELLED"
    wait_until(lambda: not slurm.leftovers(daemons=False))
    assert slurm.sacct(job_id)["State"].startswith("CANCELLED")


def test_a_job_over_its_memory_is_out_of_memory(slurm: SlurmCluster) -> None:
    job_id = slurm.sbatch(
        "#!/usr/bin/env python3\n"
        "import time\n"
        "block = bytearray(200 * 1024 * 1024)\n"
        "for i in range(0, len(block), 4096):\n"
        "    block[i] = 1\n"
        "print('survived', flush=True)\n"
        "time.sleep(5)\n", "--mem=40M")
    fields = slurm.wait_job(job_id, ENDED)
    record = slurm.sacct(job_id)
    if slurm.memory_enforcement == "cgroup":
        assert (fields["JobState"], fields["Reason"]) == ("OUT_OF_MEMORY", "OutOfMemory")
        assert record["State"] == "OUT_OF_MEMORY"
        assert "oom-kill" in slurm.output(job_id)
    else:  # jobacct_gather's polling kills it: FAILED by signal 9
        assert (fields["JobState"], fields["ExitCode"]) == ("FAILED", "0:9")
        assert "exceeded memory limit" in slurm.output(job_id)
    assert "survived" not in slurm.output(job_id)


def test_a_job_within_its_memory_completes(slurm: SlurmCluster) -> None:
    job_id = slurm.sbatch("#!/usr/bin/env python3\nblock = bytearray(10 * 1024 * 1024)\n"
                          "print('ok')\n", "--mem=60M")
    assert slurm.wait_job(job_id, ENDED)["JobState"] == "COMPLETED"


def test_a_fake_gpu_is_allocated_and_visible_to_the_job(slurm: SlurmCluster) -> None:
    job_id = slurm.sbatch('echo "gpus=$CUDA_VISIBLE_DEVICES"', "--gres=gpu:1")
    assert slurm.wait_job(job_id, ENDED)["JobState"] == "COMPLETED"
    assert slurm.output(job_id) == "gpus=0\n"
    assert slurm.job(job_id)["TresPerNode"] == "gres:gpu:1"


@pytest.mark.parametrize("request_", ["--gres=gpu:2", "--mem=2G", "--cpus-per-task=3"])
def test_a_request_no_node_can_meet_is_refused_at_submit(slurm: SlurmCluster,
                                                         request_: str) -> None:
    refused = slurm.run("sbatch", "--parsable", request_, "--wrap", "true", check=False)
    assert refused.returncode != 0
    assert "Requested node configuration is not available" in refused.stderr, refused


def test_a_killed_slurmd_fails_its_node_and_its_jobs_are_requeued_or_node_fail(
        slurm: SlurmCluster) -> None:
    marks = slurm.jobs / "requeued.txt"
    requeued = slurm.sbatch(f'echo "$SLURMD_NODENAME ${{SLURM_RESTART_COUNT:-0}}" >> {marks}\n'
                            "exec sleep 300")
    node = slurm.wait_job(requeued, ["RUNNING"])["NodeList"]
    other = next(n for n in slurm.nodes if n != node)
    failed = slurm.sbatch("exec sleep 300", "--no-requeue", f"--nodelist={node}")
    slurm.wait_job(failed, ["RUNNING"])
    t0 = time.monotonic()
    slurm.kill_slurmd(node)
    wait_until(lambda: not any("sleep 300" in cmd for _, cmd in slurm.leftovers(daemons=False)))
    slurm.wait_nodes([node], lambda s: s.endswith("*"), timeout=120)
    t_silent = time.monotonic() - t0
    slurm.wait_nodes([node], lambda s: s.startswith("down"), timeout=120)
    t_down = time.monotonic() - t0
    assert slurm.wait_job(failed, ENDED)["JobState"] == "NODE_FAIL"
    assert slurm.sacct(failed)["State"] == "NODE_FAIL"
    again = slurm.job(requeued)
    assert again["Restarts"] == "1" and again["JobState"] in ("PENDING", "RUNNING"), again
    # eligible again cred_expire + 1 s after the requeue, on the node that is still up
    rerun = slurm.wait_job(requeued, ["RUNNING"], timeout=120)
    t_rerun = time.monotonic() - t0
    assert rerun["NodeList"] == other
    wait_until(lambda: len(marks.read_text().splitlines()) >= 2)
    assert marks.read_text().split("\n")[:2] == [f"{node} 0", f"{other} 1"]
    print(f"\nnode {node} killed: not responding after {t_silent:.1f} s, DOWN after "
          f"{t_down:.1f} s, its requeued job running on {other} after {t_rerun:.1f} s "
          f"(SlurmdTimeout={slurm.slurmd_timeout})")
    slurm.start_slurmd(node)
    assert slurm.node_states()[node] == "idle"


def test_stop_leaves_nothing_running_even_after_a_test_killed_daemons() -> None:
    require_slurm()
    cluster = SlurmCluster().start()  # its own, beside the session's
    stopped = False
    try:
        for node in cluster.nodes:
            cluster.wait_job(cluster.sbatch("exec sleep 300", f"--nodelist={node}"),
                             ["RUNNING"])
        cluster.sbatch("srun sleep 301", "--nodes=2", "--ntasks-per-node=1")

        def sleeps() -> list[str]:
            return [cmd for _, cmd in cluster.leftovers(daemons=False)  # the sleeps, not srun
                    if cmd.split()[0].endswith("sleep") and "sleep 30" in cmd]

        wait_until(lambda: len(sleeps()) == 4)  # two batch jobs, two steps of the srun
        running = [pid for pid, _ in cluster.leftovers(daemons=False)]  # with slurmstepds
        daemons = [cluster.pid(d) for d in ("munged", "slurmctld", *cluster.nodes)]
        cgroups = [c for node in cluster.nodes for c in cluster.cgroups_of(node)]
        assert len(cgroups) == (4 if cluster.cgroups else 0)
        assert all(c.is_dir() for c in cgroups)
        cluster.kill_slurmd("n1")  # a node failed...
        os.kill(cluster.pid("slurmctld"), signal.SIGKILL)  # ...and the controller died
        left = cluster.stop()
        stopped = True
        assert left == []
        for pid in (*running, *daemons):
            assert not Path(f"/proc/{pid}").exists() or \
                Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z", pid
        assert not cluster.root.exists()
        assert not any(c.exists() for c in cgroups)
    finally:
        if not stopped:
            cluster.stop()
