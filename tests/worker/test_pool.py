"""LocalPool with real processes: events, outputs, kills, logs, private files."""

from __future__ import annotations

import os
import queue
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from osmo.layout import Home
from osmo.scheduler.types import (
    LOCAL_NODE,
    AttemptExited,
    AttemptPrepared,
    AttemptStarted,
    AttemptStartFailed,
    Event,
    KillAttempt,
    PrepareAttempt,
    RunAttempt,
)
from osmo.spec.model import ExitAction, ExitRule, FileSpec, TaskSpec
from osmo.worker.logread import read_log
from osmo.worker.pool import LocalPool

TIMEOUT = 30.0
Final = AttemptExited | AttemptStartFailed


class Events:
    """Collects the pool's events; waits for them with a generous timeout."""

    def __init__(self) -> None:
        self.queue: queue.Queue[Event] = queue.Queue()
        self.seen: list[Event] = []

    def __call__(self, event: Event) -> None:
        self.queue.put(event)

    def wait_for(self, match: Callable[[Event], bool]) -> Event:
        for event in self.seen:
            if match(event):
                return event
        deadline = time.monotonic() + TIMEOUT
        while True:
            event = self.queue.get(timeout=max(0.0, deadline - time.monotonic()))
            self.seen.append(event)
            if match(event):
                return event

    def final(self, attempt_id: str) -> Final:
        event = self.wait_for(
            lambda e: (
                isinstance(e, AttemptExited | AttemptStartFailed) and e.attempt_id == attempt_id
            )
        )
        assert isinstance(event, AttemptExited | AttemptStartFailed)
        return event

    def of(self, attempt_id: str) -> list[type]:
        return [type(e) for e in self.seen if getattr(e, "attempt_id", None) == attempt_id]


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            state = f.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


def attempt_dir(pool: LocalPool, attempt_id: str) -> Path | None:
    """The attempt's folder on this pool's home, if it exists."""
    dirs = pool.home.attempt_of(attempt_id)
    return dirs.root if dirs is not None and dirs.root.is_dir() else None


def wait_until(condition: Callable[[], bool]) -> None:
    deadline = time.monotonic() + TIMEOUT
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.01)


@pytest.fixture
def events() -> Events:
    return Events()


@pytest.fixture
def pool(tmp_path: Path, events: Events) -> Iterator[LocalPool]:
    pool = LocalPool(home=Home(tmp_path / "home"), emit=events, kill_grace=0.5)
    yield pool
    pool.close()


@pytest.fixture
def bare_pool(tmp_path: Path, events: Events) -> Iterator[LocalPool]:
    """Unsandboxed: for tests that read host pids (``$!``) or share host files with a task.

    (In the sandbox, pids are its own and ``/tmp`` is private: tests/runtime/test_sandbox.py.)
    """
    pool = LocalPool(home=Home(tmp_path / "home"), emit=events, kill_grace=0.5, sandbox="off")
    yield pool
    pool.close()


def submit(
    pool: LocalPool, task: TaskSpec, retry: int = 0, *, run: bool = True, **kw: dict[str, str]
) -> str:
    cmd = PrepareAttempt(
        f"wf-1:{task.name}:{retry}",
        "wf-1",
        task.name,
        retry,
        "local",
        kw.get("inputs", {}),
        kw.get("hosts", {}),
    )
    pool.prepare(cmd, task)
    if run:
        pool.run(RunAttempt(cmd.attempt_id, LOCAL_NODE))
    return cmd.attempt_id


def sh(name: str, script: str, **kw: object) -> TaskSpec:
    return TaskSpec(name=name, command=("sh", "-c", script), **kw)  # type: ignore[arg-type]


def log_of(pool: LocalPool, attempt_id: str) -> list[tuple[str, str]]:
    folder = attempt_dir(pool, attempt_id)
    assert folder is not None
    return [(r.stream, r.text) for r in read_log(folder / "log.txt")[0]]


# ---------------------------------------------------------------- lifecycle and outputs


def test_success_promotes_output(pool: LocalPool, events: Events) -> None:
    aid = submit(pool, sh("ok", "echo 42 > {{output}}/answer"))
    final = events.final(aid)
    assert isinstance(final, AttemptExited)
    assert final.exit_code == 0
    assert final.output is not None
    assert Path(final.output, "answer").read_text() == "42\n"
    assert Path(final.output).name == "output"
    assert not Path(final.output).with_name("output.partial").exists()
    assert events.of(aid) == [AttemptPrepared, AttemptStarted, AttemptExited]


def test_failure_is_not_promoted(pool: LocalPool, events: Events) -> None:
    aid = submit(pool, sh("bad", "echo partial > {{output}}/x; exit 3"))
    final = events.final(aid)
    assert isinstance(final, AttemptExited)
    assert (final.exit_code, final.output) == (3, None)
    folder = attempt_dir(pool, aid)
    assert folder is not None
    assert not (folder / "output").exists()
    assert (folder / "output.partial" / "x").read_text() == "partial\n"


def test_exit_actions_decide_promotion(pool: LocalPool, events: Events) -> None:
    rule = ExitRule(ExitAction.COMPLETE, ((3, 3),))
    final = events.final(submit(pool, sh("three", "exit 3", exit_actions=(rule,))))
    assert isinstance(final, AttemptExited) and final.output is not None
    rule = ExitRule(ExitAction.RESCHEDULE, ((0, 0),))
    final = events.final(submit(pool, sh("zero", "exit 0", exit_actions=(rule,))))
    assert isinstance(final, AttemptExited) and final.output is None


def test_exit_by_signal(pool: LocalPool, events: Events) -> None:
    final = events.final(submit(pool, sh("sig", "kill -USR1 $$")))
    assert isinstance(final, AttemptExited)
    assert final.exit_code == 128 + signal.SIGUSR1


def test_promotion_failure_is_reported(bare_pool: LocalPool, events: Events) -> None:
    final = events.final(submit(bare_pool, sh("gone", 'rmdir "$OSMO_OUTPUT"')))
    assert isinstance(final, AttemptExited)
    assert (final.exit_code, final.output) == (0, None)
    assert "outputs could not be promoted" in final.message


def test_retries_have_their_own_folders(pool: LocalPool, events: Events) -> None:
    task = sh("r", "echo $OSMO_RETRY > {{output}}/n")
    outputs = []
    for retry in (0, 1):
        final = events.final(submit(pool, task, retry))
        assert isinstance(final, AttemptExited) and final.output is not None
        outputs.append(Path(final.output, "n").read_text())
    assert outputs == ["0\n", "1\n"]


def test_inputs_and_hosts(pool: LocalPool, events: Events, tmp_path: Path) -> None:
    upstream = tmp_path / "upstream"
    upstream.mkdir()
    (upstream / "data").write_text("from a")
    task = sh(
        "down",
        "cat {{input:a}}/data > {{output}}/copy; echo {{host:peer}} > {{output}}/host",
        inputs=(),
    )
    aid = submit(pool, task, inputs={"a": str(upstream)}, hosts={"peer": "10.1.2.3"})
    final = events.final(aid)
    assert isinstance(final, AttemptExited) and final.output is not None
    assert Path(final.output, "copy").read_text() == "from a"
    assert Path(final.output, "host").read_text() == "10.1.2.3\n"


# ---------------------------------------------------------------- start failures


def test_command_not_found(pool: LocalPool, events: Events) -> None:
    aid = submit(pool, TaskSpec(name="nf", command=("no-such-command-osmo", "x")))
    final = events.final(aid)
    assert final == AttemptStartFailed(aid, "command not found: 'no-such-command-osmo'")
    assert events.of(aid) == [AttemptPrepared, AttemptStartFailed]
    assert ("osmo", "start failed: command not found: 'no-such-command-osmo'") in log_of(pool, aid)


def test_prepare_failure(pool: LocalPool, events: Events) -> None:
    aid = submit(pool, sh("tok", "echo {{input:9}}"))
    final = events.final(aid)
    assert isinstance(final, AttemptStartFailed)
    assert "{{input:9}}" in final.message
    assert events.of(aid) == [AttemptStartFailed]


def test_run_without_prepare(pool: LocalPool, events: Events) -> None:
    pool.run(RunAttempt("wf-1:ghost:0", LOCAL_NODE))
    assert isinstance(events.final("wf-1:ghost:0"), AttemptStartFailed)


# ---------------------------------------------------------------- logs


def test_logs_capture_both_streams(pool: LocalPool, events: Events) -> None:
    before = time.time()
    task = sh("logs", "echo out; echo err >&2; printf 'tab\\there'; exit 0", image="ubuntu:24.04")
    aid = submit(pool, task)
    events.final(aid)
    folder = attempt_dir(pool, aid)
    assert folder is not None
    records = read_log(folder / "log.txt")[0]
    lines = [(r.stream, r.text) for r in records]
    assert lines[0] == (
        "osmo",
        "image 'ubuntu:24.04' recorded; the process runtime runs commands on the host",
    )
    assert ("stdout", "out") in lines
    assert ("stderr", "err") in lines
    assert ("stdout", "tab\there") in lines  # the partial last line, flushed at exit
    assert lines[-1] == ("osmo", "exit code 0")
    assert all(r.ts >= before - 1 for r in records)


def test_large_output_is_not_lost(pool: LocalPool, events: Events) -> None:
    aid = submit(pool, sh("big", "seq 1 50000"))
    events.final(aid)
    out = [text for stream, text in log_of(pool, aid) if stream == "stdout"]
    assert out == [str(i) for i in range(1, 50001)]


# ---------------------------------------------------------------- kill


def test_kill_running_kills_grandchildren(bare_pool: LocalPool, events: Events) -> None:
    aid = submit(bare_pool, sh("k", "sleep 100 & echo $! > bg.pid; echo started; sleep 100"))
    started = events.wait_for(lambda e: isinstance(e, AttemptStarted))
    assert isinstance(started, AttemptStarted) and started.pid is not None
    folder = attempt_dir(bare_pool, aid)
    assert folder is not None
    wait_until(lambda: ("stdout", "started") in log_of(bare_pool, aid))
    grandchild = int((folder / "work" / "bg.pid").read_text())
    assert alive(started.pid) and started.pid_start is not None
    bare_pool.kill(KillAttempt(aid, LOCAL_NODE, "exec timeout"))
    final = events.final(aid)
    assert isinstance(final, AttemptExited)
    assert (final.exit_code, final.output) == (128 + signal.SIGTERM, None)
    assert "exec timeout" in final.message
    assert ("osmo", "killed: exec timeout") in log_of(bare_pool, aid)
    assert not (folder / "output").exists()
    wait_until(lambda: not alive(grandchild))
    assert not alive(started.pid)


def test_kill_escalates_to_sigkill(pool: LocalPool, events: Events) -> None:
    aid = submit(pool, sh("stubborn", "trap '' TERM; echo ready; sleep 100"))
    wait_until(
        lambda: attempt_dir(pool, aid) is not None and ("stdout", "ready") in log_of(pool, aid)
    )
    pool.kill(KillAttempt(aid, LOCAL_NODE, "canceled"))
    final = events.final(aid)
    assert isinstance(final, AttemptExited)
    assert final.exit_code == 128 + signal.SIGKILL


def test_killed_attempt_is_not_promoted_even_if_it_exits_zero(
    pool: LocalPool, events: Events
) -> None:
    aid = submit(
        pool, sh("graceful", "trap 'touch {{output}}/x; exit 0' TERM; echo ready; sleep 100 & wait")
    )
    wait_until(
        lambda: attempt_dir(pool, aid) is not None and ("stdout", "ready") in log_of(pool, aid)
    )
    pool.kill(KillAttempt(aid, LOCAL_NODE, "canceled"))
    final = events.final(aid)
    assert isinstance(final, AttemptExited)
    assert (final.exit_code, final.output) == (0, None)


def test_kill_before_start_reports_once(pool: LocalPool, events: Events) -> None:
    aid = submit(pool, sh("never", "echo ran > {{output}}/x"), run=False)
    pool.kill(KillAttempt(aid, LOCAL_NODE, "canceled"))
    pool.run(RunAttempt(aid, LOCAL_NODE))  # too late: must neither start nor report again
    pool.kill(KillAttempt(aid, LOCAL_NODE, "again"))
    sentinel = submit(pool, TaskSpec(name="sentinel", command=("true",)))
    final = events.final(aid)
    assert final == AttemptExited(aid, 137, None, "killed: canceled")
    events.final(sentinel)  # after its final report nothing more for `aid` follows
    # Killed while its folders were being made (no AttemptPrepared), or just after.
    assert events.of(aid) in ([AttemptExited], [AttemptPrepared, AttemptExited])


def test_kill_of_finished_or_unknown_attempt_is_ignored(pool: LocalPool, events: Events) -> None:
    aid = submit(pool, TaskSpec(name="quick", command=("true",)))
    events.final(aid)
    pool.kill(KillAttempt(aid, LOCAL_NODE, "late"))
    pool.kill(KillAttempt("wf-1:unknown:0", LOCAL_NODE, "nothing"))
    sentinel = submit(pool, TaskSpec(name="sentinel", command=("true",)))
    events.final(sentinel)
    assert events.of(aid) == [AttemptPrepared, AttemptStarted, AttemptExited]
    assert events.of("wf-1:unknown:0") == []


def test_close_kills_running_processes(tmp_path: Path, events: Events) -> None:
    pool = LocalPool(home=Home(tmp_path), emit=events)
    aid = submit(pool, sh("long", "sleep 100"))
    started = events.wait_for(lambda e: isinstance(e, AttemptStarted) and e.attempt_id == aid)
    assert isinstance(started, AttemptStarted) and started.pid is not None
    pool.close()
    assert not alive(started.pid)
    pool.close()  # idempotent


# ---------------------------------------------------------------- private files


def test_parallel_tasks_see_their_own_files(
    bare_pool: LocalPool, events: Events, tmp_path: Path
) -> None:
    """Both tasks declare /tmp/run.sh; each runs its own script while the other is alive."""
    gate = tmp_path / "gate"

    def task(name: str) -> TaskSpec:
        script = "\n".join(
            [
                "#!/bin/sh",
                f'echo {name} > "$OSMO_OUTPUT/seen"',
                f"while [ ! -e {gate} ]; do sleep 0.01; done",
                'cat /tmp/run.sh > "$OSMO_OUTPUT/script"',
                "",
            ]
        )
        return TaskSpec(
            name=name, command=("/tmp/run.sh",), files=(FileSpec("/tmp/run.sh", script),)
        )

    ids = [submit(bare_pool, task(name)) for name in ("first", "second")]
    for aid in ids:
        events.wait_for(lambda e: isinstance(e, AttemptStarted) and e.attempt_id == aid)  # noqa: B023
    gate.touch()
    for aid, name in zip(ids, ("first", "second"), strict=True):
        final = events.final(aid)
        assert isinstance(final, AttemptExited) and final.output is not None, final
        assert Path(final.output, "seen").read_text() == f"{name}\n"
        assert f"echo {name} >" in Path(final.output, "script").read_text()
        folder = attempt_dir(bare_pool, aid)
        assert folder is not None
        assert (
            Path(final.output, "script").read_text().count(str(folder / "files" / "tmp" / "run.sh"))
            == 1
        )
    if os.path.exists("/tmp/run.sh"):
        assert "OSMO_OUTPUT" not in Path("/tmp/run.sh").read_text()


# ---------------------------------------------------------------- node and helpers


def test_node_capacity(tmp_path: Path, events: Events) -> None:
    pool = LocalPool(home=Home(tmp_path), emit=events, node_id="n1", pool="p")
    try:
        node = pool.node()
        assert (node.id, node.pool) == ("n1", "p")
        assert node.capacity.cpu == float(os.cpu_count() or 1)
        assert node.capacity.memory > 0
        assert node.capacity.storage > 0
        # gpus are the NVIDIA devices the machine has (osmo.worker.machine), none here
        devices = [d for d in os.listdir("/dev") if d.startswith("nvidia") and d[6:].isdigit()]
        assert node.capacity.gpu == len(devices)
    finally:
        pool.close()
    pool = LocalPool(home=Home(tmp_path), emit=events, cpus=1.5, gpus=2, memory=1024)
    try:
        capacity = pool.node().capacity
        assert (capacity.cpu, capacity.gpu, capacity.memory) == (1.5, 2, 1024)
    finally:
        pool.close()


def test_attempt_folders_follow_the_home_layout(pool: LocalPool, events: Events) -> None:
    aid = submit(pool, TaskSpec(name="d", command=("true",)))
    events.final(aid)
    assert attempt_dir(pool, aid) == pool.home.root / "runs" / "wf-1" / "d" / "0"
    assert attempt_dir(pool, "wf-1:nothing:0") is None
    assert attempt_dir(pool, "garbage") is None


def test_many_trivial_attempts_each_report_once(pool: LocalPool, events: Events) -> None:
    ids = [submit(pool, TaskSpec(name=f"t{i}", command=("true",))) for i in range(200)]
    for aid in ids:
        final = events.final(aid)
        assert isinstance(final, AttemptExited) and final.output is not None
    for aid in ids:
        assert events.of(aid) == [AttemptPrepared, AttemptStarted, AttemptExited]


def test_background_children_end_with_the_main_process(bare_pool: LocalPool, events: Events) -> None:
    aid = submit(bare_pool, sh("bg", "sleep 100 & echo $! > bg.pid"))
    final = events.final(aid)
    assert isinstance(final, AttemptExited) and final.exit_code == 0
    folder = attempt_dir(bare_pool, aid)
    assert folder is not None
    grandchild = int((folder / "work" / "bg.pid").read_text())
    wait_until(lambda: not alive(grandchild))


def test_environment_reaches_the_command(tmp_path: Path, events: Events) -> None:
    pool = LocalPool(home=Home(tmp_path), emit=events, env={"PATH": os.environ["PATH"], "FROM": "srv"})
    try:
        task = sh(
            "env",
            'echo "$FROM $MINE $OSMO_WORKFLOW_ID $OSMO_TASK $OSMO_RETRY" > "$OSMO_OUTPUT/env"; '
            'echo "$OSMO_FILES_ROOT" > "$OSMO_OUTPUT/root"; pwd > "$OSMO_OUTPUT/cwd"',
            environment={"MINE": "{{workflow_id}}-x"},
        )
        aid = submit(pool, task, retry=2)
        final = events.final(aid)
        assert isinstance(final, AttemptExited) and final.output is not None
        out = Path(final.output)
        folder = attempt_dir(pool, aid)
        assert folder is not None
        assert (out / "env").read_text() == "srv wf-1-x wf-1 env 2\n"
        assert (out / "root").read_text() == f"{folder / 'files'}\n"
        assert (out / "cwd").read_text() == f"{folder / 'work'}\n"
    finally:
        pool.close()


def test_prepare_with_run_flag_starts_without_run_call(pool: LocalPool, events: Events) -> None:
    task = sh("self", "echo started > {{output}}/x")
    cmd = PrepareAttempt("wf-1:self:0", "wf-1", "self", 0, "local", {}, {}, run=True)
    pool.prepare(cmd, task)
    final = events.final(cmd.attempt_id)
    assert isinstance(final, AttemptExited) and final.exit_code == 0 and final.output
    assert Path(final.output, "x").read_text() == "started\n"
    assert events.of(cmd.attempt_id) == [AttemptPrepared, AttemptStarted, AttemptExited]


def test_many_attempts_prepare_concurrently_and_each_reports_once(
        pool: LocalPool, events: Events) -> None:
    ids = [submit(pool, sh(f"t{i}", f"echo {i} > {{{{output}}}}/n")) for i in range(40)]
    for i, aid in enumerate(ids):
        final = events.final(aid)
        assert isinstance(final, AttemptExited) and final.output
        assert Path(final.output, "n").read_text() == f"{i}\n"
    for aid in ids:
        assert events.of(aid) == [AttemptPrepared, AttemptStarted, AttemptExited]
