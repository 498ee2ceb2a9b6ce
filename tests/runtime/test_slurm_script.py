"""The Slurm runtime's pure parts: sbatch's options (osmo.runtime.slurm.script), the pyxis
argv, and the one state table (osmo.runtime.slurm.states). The runtime itself runs on a real
cluster in tests/runtime/test_contract.py and tests/slurm/."""

from __future__ import annotations

from pathlib import Path

import pytest

from osmo.errors import UsageError
from osmo.options import SlurmOptions
from osmo.runtime.api import PrepareError, Terms
from osmo.runtime.container.run import Mount
from osmo.runtime.slurm.commands import gpus_of, minutes_of
from osmo.runtime.slurm.script import gang_args, pyxis_argv, resource_args, sbatch_args
from osmo.runtime.slurm.states import REASONS, Phase, verdict, waiting_reason
from osmo.spec.model import ResourceSpec

MI = 1 << 20


def test_resources_become_one_option_word_each() -> None:
    args = sbatch_args(name="osmo-t-1", owner="own", folder=Path("/f"),
                       resources=ResourceSpec(cpu=3, gpu=2, memory=1536 * MI + 1,
                                              storage=10 * MI, platform="gpu"),
                       options=SlurmOptions(partitions=("cpu", "gpu"), account="acct",
                                            qos="high", constraint="a100"))
    assert args == ["--job-name=osmo-t-1", "--comment=own", "--chdir=/f", "--output=/f/out",
                    "--error=/f/err", "--open-mode=append", "--export=NONE", "--nodes=1",
                    "--ntasks=1", "--cpus-per-task=3", "--mem=1537M", "--gres=gpu:2",
                    "--tmp=10M", "--partition=gpu", "--account=acct", "--qos=high",
                    "--constraint=a100"]
    plain = resource_args(ResourceSpec(), SlurmOptions(partitions=("a", "b")))
    assert plain == ["--nodes=1", "--ntasks=1", "--cpus-per-task=1", "--partition=a,b"]


@pytest.mark.parametrize("timeout, time", [(3, "1"), (60, "1"), (61, "2"), (7200, "120")])
def test_exec_timeout_is_the_job_s_time_in_whole_minutes_rounded_up(timeout: float,
                                                                    time: str) -> None:
    args = resource_args(ResourceSpec(), SlurmOptions(), Terms(exec_timeout=timeout))
    assert [a for a in args if a.startswith("--time")] == [f"--time={time}"]
    assert not any(a.startswith("--time") for a in resource_args(ResourceSpec(),
                                                                 SlurmOptions()))


@pytest.mark.parametrize("priority, nice", [("HIGH", None), ("NORMAL", "--nice=100"),
                                            ("LOW", "--nice=200"), (None, None)])
def test_priority_is_nice(priority: str | None, nice: str | None) -> None:
    args = resource_args(ResourceSpec(), SlurmOptions(), Terms(priority=priority))
    assert [a for a in args if a.startswith("--nice")] == ([nice] if nice else [])
    off = resource_args(ResourceSpec(), SlurmOptions(nice=0), Terms(priority="LOW"))
    assert not any(a.startswith("--nice") for a in off)


def test_a_priority_s_configured_qos_replaces_the_pool_s() -> None:
    options = SlurmOptions(qos="normal", priority_qos=(("HIGH", "urgent"),))
    high = resource_args(ResourceSpec(), options, Terms(priority="HIGH"))
    low = resource_args(ResourceSpec(), options, Terms(priority="LOW"))
    assert "--qos=urgent" in high and "--qos=normal" not in high
    assert "--qos=normal" in low
    with pytest.raises(UsageError, match="only letters"):
        SlurmOptions(priority_qos=(("HIGH", "a b"),)).check()


def test_a_gang_is_one_heterogeneous_job() -> None:
    args = gang_args(name="g", owner="o", folder=Path("/f"),
                     components=[["--cpus-per-task=1"], ["--cpus-per-task=2"]])
    assert args[-3:] == ["--cpus-per-task=1", ":", "--cpus-per-task=2"]
    assert "--output=/f/gang.log" in args and "--error=/f/gang.log" in args


@pytest.mark.parametrize("flag, value", [("partitions", ("a b",)), ("account", "x\n#SBATCH"),
                                         ("qos", "--mem=1"), ("constraint", "a;b")])
def test_a_configured_value_that_is_not_a_plain_slurm_word_is_refused(flag: str,
                                                                      value: object) -> None:
    with pytest.raises(UsageError, match="only letters"):
        SlurmOptions(**{flag: value}).check()  # type: ignore[arg-type]


def test_pyxis_runs_the_task_in_its_image_with_osmo_s_layout_bound() -> None:
    argv = pyxis_argv("/usr/bin/srun", "nvcr.io/nvidia/pytorch:24.01-py3",
                      [Mount(Path("/h/out"), "/osmo/data/output", read_only=False),
                       Mount(Path("/h/in0"), "/osmo/data/input/0")], "/osmo/run/work",
                      ["python", "-c", "print(1)"])
    assert argv == ["/usr/bin/srun", "--ntasks=1", "--nodes=1",
                    "--container-image=nvcr.io/nvidia/pytorch:24.01-py3",
                    "--no-container-mount-home",
                    "--container-mounts=/h/out:/osmo/data/output,/h/in0:/osmo/data/input/0:ro",
                    "--container-workdir=/osmo/run/work", "--", "python", "-c", "print(1)"]
    with pytest.raises(PrepareError, match="pyxis cannot bind"):
        pyxis_argv("srun", "img", [Mount(Path("/h/a,b"), "/x")], None, ["true"])


@pytest.mark.parametrize("state, phase, code, override", [
    ("PENDING", Phase.WAITING, None, False), ("REQUEUED", Phase.WAITING, None, False),
    ("RUNNING", Phase.RUNNING, None, False), ("COMPLETING", Phase.RUNNING, None, False),
    ("COMPLETED", Phase.ENDED, 0, False), ("FAILED", Phase.ENDED, 1, False),
    ("CANCELLED by 0", Phase.ENDED, 137, False), ("OUT_OF_MEMORY", Phase.ENDED, 137, True),
    ("TIMEOUT", Phase.ENDED, 137, False), ("NODE_FAIL", Phase.LOST, None, False),
    ("PREEMPTED", Phase.LOST, None, False), ("BOOT_FAIL", Phase.LOST, None, False),
    ("SOMETHING_NEW", Phase.RUNNING, None, False),
])
def test_the_state_table(state: str, phase: Phase, code: int | None, override: bool) -> None:
    seen = verdict(state)
    assert (seen.phase, seen.code, seen.override) == (phase, code, override)
    assert verdict("SOMETHING_NEW", listed=False).phase is Phase.ENDED


@pytest.mark.parametrize("reason", sorted(REASONS))
def test_each_known_pending_reason_is_said_in_words(reason: str) -> None:
    said = waiting_reason("12", "PENDING", reason)
    assert said == f"Slurm job 12 PENDING: {reason} ({REASONS[reason]})"


@pytest.mark.parametrize(("state", "reason", "said"), [
    ("PENDING", "SomeNewReason", "Slurm job 7 PENDING: SomeNewReason"),
    ("REQUEUE_HOLD", "", "Slurm job 7 REQUEUE_HOLD: None"),
    ("PENDING", "None", "Slurm job 7 PENDING: None"),
])
def test_any_other_pending_reason_is_shown_as_slurm_says_it(state: str, reason: str,
                                                            said: str) -> None:
    assert waiting_reason("7", state, reason) == said


def test_gpus_are_read_from_gres() -> None:
    assert gpus_of("gpu:2") == 2 and gpus_of("gpu:a100:4(S:0-1),mps:100") == 4
    assert gpus_of("(null)") == 0 and gpus_of("gpu:1,gpu:v100:2") == 3


def _worker_slurm_options(*flags: str) -> SlurmOptions:
    import argparse

    from osmo.worker.options import WorkerOptions

    parser = argparse.ArgumentParser()
    WorkerOptions.add_arguments(parser)
    args = parser.parse_args(["--connect", "tcp/127.0.0.1:1", "--token", "t", *flags])
    return WorkerOptions.from_args(args).slurm


def test_the_worker_s_priority_flags() -> None:
    made = _worker_slurm_options("--slurm-nice", "50", "--slurm-priority-qos", "high=urgent")
    assert (made.nice, made.priority_qos) == (50, (("HIGH", "urgent"),))
    assert _worker_slurm_options().nice == 100
    for bad in (["--slurm-priority-qos", "URGENT=x"], ["--slurm-priority-qos", "HIGH"],
                ["--slurm-priority-qos", "HIGH=a;b"], ["--slurm-nice", "-5"]):
        with pytest.raises(UsageError):
            _worker_slurm_options(*bad)


@pytest.mark.parametrize("shown, minutes", [("infinite", None), ("UNLIMITED", None),
                                            ("5", 5), ("1:00", 1), ("1:01", 2),
                                            ("2:03:04", 124), ("1-00:00:00", 1440),
                                            ("n/a", None), ("1-x", None)])
def test_partition_time_limits_as_sinfo_shows_them(shown: str, minutes: int | None) -> None:
    assert minutes_of(shown) == minutes
