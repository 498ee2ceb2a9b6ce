"""The process runtime with real processes: spawn, exit codes, group kill, stale clean-up."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from osmo.runtime import (
    Launch,
    ProcessGroups,
    ProcessHandle,
    StartError,
    exit_code_of,
    kill_stale,
    process_start_time,
)
from osmo.runtime.process.warm import WarmHandle, WarmRunners, commands_key
from osmo.worker.taskenv import base_env

TIMEOUT = 30.0


def alive(pid: int) -> bool:
    """True if ``pid`` exists and is not a zombie (orphans may wait for a lazy init)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            state = f.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


def wait_until(condition: Callable[[], bool], timeout: float = TIMEOUT) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.01)


def wait_exit(handle: ProcessHandle) -> None:
    readable, _, _ = select.select([handle.exit_fd], [], [], TIMEOUT)
    assert readable, "process did not exit in time"


def read_all(fd: int) -> bytes:
    chunks: list[bytes] = []
    while True:
        readable, _, _ = select.select([fd], [], [], TIMEOUT)
        assert readable
        data = os.read(fd, 65536)
        if not data:
            return b"".join(chunks)
        chunks.append(data)


class _Warm:
    """``ProcessGroups``' calls over warm runners: each command forked from one, then exec'd."""

    def __init__(self) -> None:
        self.runners = WarmRunners(base_env(os.environ))

    def start(self, argv: list[str], *, cwd: Path, env: dict[str, str]) -> ProcessHandle:
        return self.runners.start(commands_key(), Launch(tuple(argv), cwd, env))

    def kill(self, handle: ProcessHandle, *, force: bool = False) -> None:
        assert isinstance(handle, WarmHandle)
        self.runners.kill(handle, force=force)

    def reap(self, handle: ProcessHandle) -> int:
        assert isinstance(handle, WarmHandle)
        return self.runners.reap(handle)

    def release(self, handle: ProcessHandle) -> None:
        assert isinstance(handle, WarmHandle)
        self.runners.release(handle)


@pytest.fixture(params=["cold", "warm"])
def runtime(request: pytest.FixtureRequest) -> Iterator[ProcessGroups]:
    """Plain process groups, and the same calls over a warm runner's forks."""
    if request.param == "cold":
        yield ProcessGroups()
        return
    warm = _Warm()
    yield warm  # type: ignore[misc]
    assert [r.started > 0 for r in warm.runners.runners()] in ([True], []), "not forked warm"
    warm.runners.close()


def start(runtime: ProcessGroups, script: str, cwd: Path) -> ProcessHandle:
    return runtime.start(["sh", "-c", script], cwd=cwd, env={"PATH": os.environ["PATH"]})


@pytest.mark.parametrize(
    ("script", "code"),
    [("true", 0), ("exit 3", 3), ("exit 255", 255), ("kill -TERM $$", 143), ("kill -KILL $$", 137)],
)
def test_exit_codes_are_normalised(
    runtime: ProcessGroups, tmp_path: Path, script: str, code: int
) -> None:
    handle = start(runtime, script, tmp_path)
    wait_exit(handle)
    assert runtime.reap(handle) == code
    runtime.release(handle)


def test_exit_code_of() -> None:
    assert exit_code_of(0) == 0
    assert exit_code_of(-9) == 137
    assert exit_code_of(2) == 2


def test_cwd_env_and_pipes(runtime: ProcessGroups, tmp_path: Path) -> None:
    handle = runtime.start(
        ["sh", "-c", 'pwd; echo "$ONLY"; echo err >&2'],
        cwd=tmp_path,
        env={"PATH": os.environ["PATH"], "ONLY": "this"},
    )
    out, err = read_all(handle.stdout_fd), read_all(handle.stderr_fd)
    wait_exit(handle)
    assert runtime.reap(handle) == 0
    runtime.release(handle)
    assert out.decode().splitlines() == [str(tmp_path), "this"]
    assert err == b"err\n"


def test_runs_in_its_own_process_group(runtime: ProcessGroups, tmp_path: Path) -> None:
    handle = start(runtime, "sleep 100", tmp_path)
    try:
        assert os.getpgid(handle.pid) == handle.pid
        assert os.getsid(handle.pid) == handle.pid
    finally:
        runtime.kill(handle, force=True)
        wait_exit(handle)
        runtime.reap(handle)
        runtime.release(handle)


def test_kill_reaches_grandchildren(runtime: ProcessGroups, tmp_path: Path) -> None:
    handle = start(runtime, "sleep 100 & echo $!; sleep 100", tmp_path)
    line = b""
    while not line.endswith(b"\n"):
        select.select([handle.stdout_fd], [], [], TIMEOUT)
        line += os.read(handle.stdout_fd, 100)
    grandchild = int(line)
    assert alive(grandchild)
    runtime.kill(handle)
    wait_exit(handle)
    assert runtime.reap(handle) == 128 + signal.SIGTERM
    runtime.release(handle)
    wait_until(lambda: not alive(grandchild))


def test_reap_kills_leftover_background_children(runtime: ProcessGroups, tmp_path: Path) -> None:
    pid_file = tmp_path / "bg.pid"
    handle = start(runtime, f"sleep 100 & echo $! > {pid_file}", tmp_path)
    wait_exit(handle)
    assert runtime.reap(handle) == 0
    runtime.release(handle)
    wait_until(lambda: not alive(int(pid_file.read_text())))


def test_kill_after_reap_is_harmless(runtime: ProcessGroups, tmp_path: Path) -> None:
    """After reap the group id may name someone else's group, and after release the fd
    numbers may be someone else's files: neither a late kill nor a second release touches
    them."""
    handle = start(runtime, "true", tmp_path)
    wait_exit(handle)
    runtime.reap(handle)
    # Stand-in for a recycled pid: a live process group of ours under the handle's pid.
    other = subprocess.Popen(["sleep", "30"], start_new_session=True)
    try:
        handle.pid = other.pid
        runtime.kill(handle, force=True)
        runtime.kill(handle)
        time.sleep(0.2)  # a signal, if one had been sent, has landed by now
        assert other.poll() is None, "a kill after reap signalled another process group"
    finally:
        other.kill()
        other.wait()
    numbers = {handle.exit_fd, handle.stdout_fd, handle.stderr_fd}
    runtime.release(handle)
    reused = [os.open(os.devnull, os.O_RDONLY) for _ in range(6)]  # take the freed numbers
    try:
        assert numbers & set(reused), "the freed fd numbers were not reused; test is moot"
        runtime.release(handle)
        for fd in reused:
            os.fstat(fd)  # raises EBADF if the second release closed someone else's fd
    finally:
        for fd in reused:
            os.close(fd)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["no-such-command-osmo"], "command not found: 'no-such-command-osmo'"),
        (["/no/such/path/tool"], "command not found: '/no/such/path/tool'"),
        ([], "empty command"),
    ],
)
def test_start_errors(
    runtime: ProcessGroups, tmp_path: Path, argv: list[str], message: str
) -> None:
    with pytest.raises(StartError) as info:
        runtime.start(argv, cwd=tmp_path, env={"PATH": os.environ["PATH"]})
    assert str(info.value) == message


def test_start_error_not_executable(runtime: ProcessGroups, tmp_path: Path) -> None:
    script = tmp_path / "script.sh"
    script.write_text("#!/bin/sh\ntrue\n")
    script.chmod(0o644)
    with pytest.raises(StartError, match="not executable"):
        runtime.start([str(script)], cwd=tmp_path, env={})


@pytest.mark.parametrize(
    ("head", "message"),
    [
        ("#!/no/such/interpreter\ntrue\n", "command not found: '{path}'"),
        ("true\n", "cannot start '{path}': Exec format error"),  # no shebang, no binary
    ],
)
def test_start_error_of_a_file_the_kernel_cannot_execute(
    runtime: ProcessGroups, tmp_path: Path, head: str, message: str
) -> None:
    """What execve refuses fails the start, as a spawn does (a shell would run the second)."""
    script = tmp_path / "script"
    script.write_text(head)
    script.chmod(0o755)
    with pytest.raises(StartError) as info:
        runtime.start([str(script)], cwd=tmp_path, env={"PATH": os.environ["PATH"]})
    assert str(info.value) == message.format(path=script)


def test_a_program_named_like_an_option_runs_as_the_program(
    runtime: ProcessGroups, tmp_path: Path
) -> None:
    """A hostile name (``--pdeathsig``) is the task's program, never a wrapper's option."""
    folder = tmp_path / "bin"
    folder.mkdir()
    script = folder / "--pdeathsig"
    script.write_text("#!/bin/sh\necho ran \"$@\"\n")
    script.chmod(0o755)
    handle = runtime.start(["--pdeathsig", "KILL", "--help"], cwd=tmp_path,
                           env={"PATH": f"{folder}:{os.environ['PATH']}"})
    try:
        assert read_all(handle.stdout_fd) == b"ran KILL --help\n"
        wait_exit(handle)
        assert runtime.reap(handle) == 0
    finally:
        runtime.release(handle)


def test_start_error_missing_cwd(runtime: ProcessGroups, tmp_path: Path) -> None:
    with pytest.raises(StartError, match="working folder not found"):
        runtime.start(["true"], cwd=tmp_path / "gone", env={"PATH": os.environ["PATH"]})


# ---------------------------------------------------------------- stale clean-up


def spawn_group(script: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(["sh", "-c", script], start_new_session=True, stdout=subprocess.PIPE)


def test_process_start_time_is_stable() -> None:
    proc = spawn_group("sleep 100")
    try:
        first = process_start_time(proc.pid)
        assert first is not None
        assert abs(first - time.time()) < 3600
        assert process_start_time(proc.pid) == first
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        assert proc.stdout is not None
        proc.stdout.close()
    assert process_start_time(proc.pid) is None


def test_kill_stale_refuses_a_different_process() -> None:
    proc = spawn_group("sleep 100")
    try:
        started = process_start_time(proc.pid)
        assert started is not None
        assert not kill_stale(proc.pid, started - 1000)
        assert alive(proc.pid)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        assert proc.stdout is not None
        proc.stdout.close()


def test_kill_stale_kills_the_same_group_with_grandchildren() -> None:
    proc = spawn_group("sleep 100 & echo $!; sleep 100")
    assert proc.stdout is not None
    grandchild = int(proc.stdout.readline())
    started = process_start_time(proc.pid)
    assert started is not None
    assert kill_stale(proc.pid, started)
    assert proc.wait() == -signal.SIGKILL
    proc.stdout.close()
    wait_until(lambda: not alive(grandchild))


def test_kill_stale_kills_orphans_of_a_dead_leader() -> None:
    proc = spawn_group("sleep 100 & echo $!")
    assert proc.stdout is not None
    grandchild = int(proc.stdout.readline())
    started = process_start_time(proc.pid)
    assert started is not None
    assert proc.wait() == 0  # the leader is gone; its background child keeps the group
    proc.stdout.close()
    assert alive(grandchild)
    assert kill_stale(proc.pid, started)
    wait_until(lambda: not alive(grandchild))


def test_kill_stale_of_a_gone_group_is_false() -> None:
    proc = spawn_group("true")
    started = process_start_time(proc.pid) or time.time()
    proc.wait()
    assert proc.stdout is not None
    proc.stdout.close()
    assert not kill_stale(proc.pid, started)


# ---------------------------------------------------------------- a warm runner's spare child


def _children(pid: int) -> list[int]:
    """Live (not zombie) children of ``pid``."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid and fields[0] not in ("Z", "X"):
                out.append(int(entry))
    return out


def _run_true(warm: _Warm, tmp_path: Path) -> ProcessHandle:
    handle = warm.start(["true"], cwd=tmp_path, env={"PATH": os.environ["PATH"]})
    wait_exit(handle)
    assert warm.reap(handle) == 0
    warm.release(handle)
    return handle


def test_a_warm_runner_forks_the_next_attempt_ahead_of_its_request(tmp_path: Path) -> None:
    """The fork is off the start's path: the next attempt is the child forked beforehand,
    which leads its own session and holds nothing but its socket to the runner. Its handle
    has the process's own start time (what ``kill_stale`` matches after a crash), not the
    request's."""
    warm = _Warm()
    try:
        _run_true(warm, tmp_path)
        [runner] = warm.runners.runners()
        wait_until(lambda: len(_children(runner.pid)) == 1)
        [spare] = _children(runner.pid)
        assert os.getsid(spare) == spare and os.getpgid(spare) == spare
        fds = {n: os.readlink(f"/proc/{spare}/fd/{n}") for n in os.listdir(f"/proc/{spare}/fd")}
        extra = {n: target for n, target in fds.items() if n not in ("0", "1", "2")}
        assert len(extra) == 1 and next(iter(extra.values())).startswith("socket:"), fds
        time.sleep(1.0)  # the spare is older than the request
        handle = warm.start(["sh", "-c", "echo $$"], cwd=tmp_path,
                            env={"PATH": os.environ["PATH"]})
        assert handle.pid == spare
        assert handle.started_at == process_start_time(spare)
        assert read_all(handle.stdout_fd) == f"{spare}\n".encode()
        wait_exit(handle)
        assert warm.reap(handle) == 0
        warm.release(handle)
    finally:
        warm.runners.close()


def test_a_spare_killed_from_outside_is_replaced(tmp_path: Path) -> None:
    warm = _Warm()
    try:
        _run_true(warm, tmp_path)
        [runner] = warm.runners.runners()
        wait_until(lambda: len(_children(runner.pid)) == 1)
        [spare] = _children(runner.pid)
        os.kill(spare, signal.SIGKILL)
        wait_until(lambda: spare not in _children(runner.pid))
        handle = _run_true(warm, tmp_path)
        assert handle.pid != spare
        assert [r.pid for r in warm.runners.runners()] == [runner.pid]  # the same runner
    finally:
        warm.runners.close()
    wait_until(lambda: not alive(runner.pid))
