"""The runtime conformance kit: :func:`check_runtime`.

For runtimes (``osmo.runtime.api.Runtime``: the process runtime, plain and sandboxed, the
container runtime, and the Kubernetes or Slurm runtimes to come). A new runtime is done when
it passes::

    from osmo.testing import check_runtime

    def test_my_runtime_keeps_the_contract(tmp_path):
        check_runtime(MyRuntime(...), tmp_path, image="alpine:3.18")

It prepares real attempts the way the worker pool does (``osmo.worker.workdir.prepare`` with
the runtime's ``paths``, then ``Runtime.prepare``), runs them through the runtime alone
(start, the handle's pipes and exit descriptor, kill, reap, release, clean-up), and fails
with an ``AssertionError`` listing every broken promise:

1. ``describe`` says something; ``paths`` gives ``Paths``; ``prepare`` keeps the command;
2. a task's stdout and stderr arrive on the handle's pipes (either pipe, for a runtime
   checked with ``merged_output=True``: a pod has one log), its exit code comes back from
   ``reap``, what it writes to ``{{output}}`` (and ``$OSMO_OUTPUT``) lands in the attempt's
   ``output.partial`` folder, and a credential variable reaches it without appearing in its
   argv, nor in any file of the attempt's folder once it was released and cleaned up;
3. ``kill`` (SIGTERM) ends a running task with exit code 143; a task that ignores SIGTERM
   ends with 137 after ``kill(force=True)``; killing a released handle is harmless;
4. a command that cannot run fails its start (``StartError``) or exits non-zero at once;
5. ``exec`` runs a command beside the running task, in its environment;
6. ``connector`` reaches a port the task listens on.

The tasks need ``sh``, ``sleep``, ``echo`` and a listener (``listen``, default ``nc -l -p
PORT``) where the runtime runs them; ``image`` is given to tasks for a runtime that runs
them in their image. The kit leaves nothing running; what it leaves in ``folder`` is the
attempts' folders. The runtime stays open (close it yourself).
"""

from __future__ import annotations

import os
import selectors
import subprocess
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from osmo.runtime.api import Launch, ProcessHandle, Runtime

__all__ = ["Pipes", "check_runtime"]

_SECRET = "conformance-s3cr3t-V4lue"
_TERM, _KILL = 128 + 15, 128 + 9


def check_runtime(runtime: Runtime, folder: str | os.PathLike[str], *,
                  image: str | None = None, listen: Sequence[str] = ("nc", "-l", "-p", "{port}"),
                  timeout: float = 60.0, merged_output: bool = False) -> None:
    """Check that ``runtime`` keeps the runtime contract (see the module docstring).

    Args:
        runtime: the runtime under test, ready to run attempts on this machine.
        folder: where the attempts' folders are made (an empty folder of the test's).
        image: the image every task names (for a runtime that runs tasks in their image).
        listen: argv of a TCP listener that prints what it receives, ``{port}`` its port.
        timeout: seconds to wait for each step.
        merged_output: the runtime's engine keeps one log for both streams (a pod's): the
            task's stdout and stderr lines may arrive on either pipe.

    Raises:
        AssertionError: listing every broken promise.
    """
    check = _RuntimeCheck(runtime, Path(folder).absolute(), image, tuple(listen), timeout,
                          merged_output)
    for step in (check.describes, check.runs, check.exits, check.terminates, check.kills,
                 check.fails_to_start, check.execs, check.connects):
        try:
            step()
        except Exception as exc:  # noqa: BLE001 - a step's failure is a problem found
            check.problems.append(f"{step.__name__}: {type(exc).__name__}: {exc}")
        finally:
            check.stop_all()
    if check.problems:
        raise AssertionError(f"{runtime!r} breaks the runtime contract:\n  - "
                             + "\n  - ".join(check.problems))


class Pipes:
    """A started launch's pipes and exit, read as the pool's reactor reads them.

    Attributes:
        handle: the launch's handle.
        out, err: what its stdout and stderr gave so far.
        eof: the pipes that reached their end.
    """

    def __init__(self, handle: ProcessHandle) -> None:
        self.handle = handle
        self.out, self.err = bytearray(), bytearray()
        self.eof: set[int] = set()

    def ended(self) -> bool:
        """Whether the launch ended (its exit descriptor is readable)."""
        with selectors.DefaultSelector() as sel:
            sel.register(self.handle.exit_fd, selectors.EVENT_READ)
            return bool(sel.select(0))

    def pump(self, wait: float) -> bool:
        """Read what the open pipes hold (waiting up to ``wait``); True if bytes came."""
        got = False
        with selectors.DefaultSelector() as sel:
            sel.register(self.handle.exit_fd, selectors.EVENT_READ, None)
            for fd, buf in ((self.handle.stdout_fd, self.out), (self.handle.stderr_fd, self.err)):
                if fd not in self.eof:
                    sel.register(fd, selectors.EVENT_READ, buf)
            for key, _ in sel.select(wait):
                if key.data is None:
                    continue
                try:
                    data = os.read(key.fd, 65536)
                except BlockingIOError:
                    continue
                if not data:
                    self.eof.add(key.fd)
                key.data.extend(data)
                got = got or bool(data)
        return got

    def until(self, text: bytes, timeout: float) -> bool:
        """Read until ``text`` is in stdout; False when it ended or the time ran out first."""
        deadline = time.monotonic() + timeout
        while text not in self.out:
            if (len(self.eof) == 2 and self.ended()) or time.monotonic() > deadline:
                return False
            self.pump(0.1)
        return True


class _Started(Pipes):
    """A started launch of the check, and its exit code once reaped."""

    def __init__(self, runtime: Runtime, launch: Launch, handle: ProcessHandle) -> None:
        super().__init__(handle)
        self.runtime, self.launch = runtime, launch
        self.code: int | None = None

    def finish(self, timeout: float) -> int | None:
        """Wait for its end, read the rest, reap and release; the exit code (None: no end)."""
        deadline = time.monotonic() + timeout
        while not self.ended():
            if time.monotonic() > deadline:
                return None
            self.pump(0.1)
        for _ in range(64):
            if not self.pump(0):
                break
        self.code = self.runtime.reap(self.handle)
        self.runtime.release(self.handle)
        return self.code


class _RuntimeCheck:
    """The steps of :func:`check_runtime` and the problems they found."""

    def __init__(self, runtime: Runtime, root: Path, image: str | None,
                 listen: tuple[str, ...], timeout: float, merged_output: bool = False) -> None:
        self.runtime, self.root, self.image = runtime, root, image
        self.listen, self.timeout = listen, timeout
        self.merged_output = merged_output
        self.workflow_id = f"conformance-{uuid.uuid4().hex[:8]}"
        self.problems: list[str] = []
        self._running: list[_Started] = []

    def launch(self, name: str, command: Sequence[str], *,
               environment: Mapping[str, str] | None = None,
               credentials: Mapping[str, Any] | None = None,
               secrets: Mapping[str, Mapping[str, str]] | None = None) -> Launch:
        """Prepare an attempt of a task ``name`` running ``command``, as the pool does."""
        from osmo.layout import AttemptDirs
        from osmo.runtime.api import Attempt, Paths
        from osmo.scheduler.types import PrepareAttempt
        from osmo.spec.model import TaskSpec
        from osmo.worker.taskenv import base_env
        from osmo.worker.workdir import prepare

        task = TaskSpec(name, image=self.image, command=tuple(command),
                        environment=dict(environment or {}), credentials=dict(credentials or {}))
        cmd = PrepareAttempt(f"{self.workflow_id}:{name}:0", self.workflow_id, name, 0,
                             "conformance", {}, {})
        dirs = AttemptDirs(self.root / self.workflow_id / name / "0")
        paths = self.runtime.paths(cmd)
        if not isinstance(paths, Paths):
            self.problems.append(f"paths() gave {paths!r}, not Paths")
            paths = Paths()
        made = prepare(dirs, cmd, task, base_env(os.environ), secrets or {}, paths=paths)
        lines: list[str] = []
        launch = self.runtime.prepare(made, Attempt(cmd, task, dirs), progress=lines.append)
        if launch.argv != made.argv or launch.cwd != made.cwd:
            self.problems.append(f"{name}: prepare() changed the command or its folder")
        return launch

    def start(self, launch: Launch) -> _Started:
        started = _Started(self.runtime, launch, self.runtime.start(launch))
        self._running.append(started)
        return started

    def stop_all(self) -> None:
        """Kill, reap, release and clean up what a step left running."""
        for started in self._running:
            if started.code is None:
                started.runtime.kill(started.handle, force=True)
                if started.finish(self.timeout) is None:
                    self.problems.append(f"{started.launch.argv}: still running after a "
                                         "forced kill")
            self.runtime.cleanup(started.launch)
        self._running.clear()

    def expect(self, ok: bool, problem: str) -> None:
        if not ok:
            self.problems.append(problem)

    # -------------------------------------------------------------- the steps

    def describes(self) -> None:
        """It says how it runs tasks."""
        said = self.runtime.describe()
        self.expect(isinstance(said, str) and bool(said), f"describe() gave {said!r}")

    def runs(self) -> None:
        """Pipes, exit code, the output folder, a credential variable, no secret left."""
        script = ('echo out; echo err >&2; echo hi > {{output}}/hello.txt; '
                  'echo "$OSMO_TASK" > "$OSMO_OUTPUT/task.txt"; '
                  'case "$TOKEN" in conformance-*-V4lue) echo has-token;; esac')
        launch = self.launch("ok", ["sh", "-c", script], credentials={"api": {"TOKEN": "token"}},
                             secrets={"api": {"token": _SECRET}})
        self.expect(not any(_SECRET in word for word in launch.argv),
                    "ok: a credential variable's value is in the argv")
        started = self.start(launch)
        code = started.finish(self.timeout)
        out, err = bytes(started.out).split(), bytes(started.err).split()
        self.expect(code == 0, f"ok: exit code {code}, expected 0 (stderr {bytes(started.err)!r})")
        both = out + err if self.merged_output else None  # one log: no stream of its own
        self.expect(b"out" in (both or out) and b"err" in (both or err),
                    f"ok: stdout {bytes(started.out)!r}, stderr {bytes(started.err)!r}")
        self.expect(b"has-token" in out, "ok: the credential variable did not reach the task")
        output = launch.cwd.parent / "output.partial"
        for name, text in (("hello.txt", "hi"), ("task.txt", "ok")):
            found = (output / name).read_text().strip() if (output / name).is_file() else None
            self.expect(found == text, f"ok: {output / name} holds {found!r}, expected {text!r}")
        self.runtime.cleanup(launch)
        self.runtime.cleanup(launch)  # idempotent
        self._running.remove(started)
        left = [str(p) for p in launch.cwd.parent.rglob("*")
                if p.is_file() and _SECRET.encode() in p.read_bytes()]
        self.expect(not left, f"ok: the secret is left in {left}")
        self.runtime.kill(started.handle)  # released: harmless
        self.runtime.kill(started.handle, force=True)

    def exits(self) -> None:
        """The exit code comes back."""
        code = self.start(self.launch("exit3", ["sh", "-c", "exit 3"])).finish(self.timeout)
        self.expect(code == 3, f"exit3: exit code {code}, expected 3")

    def terminates(self) -> None:
        """SIGTERM ends a running task (143)."""
        started = self.start(self.launch("term", ["sh", "-c", "echo ready; exec sleep 300"]))
        if not started.until(b"ready", self.timeout):
            self.problems.append(f"term: never ran (stderr {bytes(started.err)!r})")
            return
        self.runtime.kill(started.handle)
        code = started.finish(self.timeout)
        self.expect(code == _TERM, f"term: exit code {code} after SIGTERM, expected {_TERM}")

    def kills(self) -> None:
        """A task that ignores SIGTERM ends with a forced kill (137)."""
        script = "trap '' TERM; echo ready; sleep 300; echo survived"
        started = self.start(self.launch("stubborn", ["sh", "-c", script]))
        if not started.until(b"ready", self.timeout):
            self.problems.append(f"stubborn: never ran (stderr {bytes(started.err)!r})")
            return
        self.runtime.kill(started.handle)
        time.sleep(0.5)
        self.expect(not started.ended(), "stubborn: SIGTERM, which it ignores, ended it")
        self.runtime.kill(started.handle, force=True)
        code = started.finish(self.timeout)
        self.expect(code == _KILL, f"stubborn: exit code {code} after a forced kill, "
                                   f"expected {_KILL}")

    def fails_to_start(self) -> None:
        """A command that cannot run fails its start or exits non-zero."""
        from osmo.runtime.api import StartError

        launch = self.launch("missing", ["osmo-conformance-no-such-command"])
        try:
            started = self.start(launch)
        except StartError:
            self.runtime.cleanup(launch)
            return
        code = started.finish(self.timeout)
        self.expect(code not in (0, None), f"missing: exit code {code}, expected a failure")

    def execs(self) -> None:
        """``exec`` runs beside the task, in its environment."""
        started = self.start(self.launch("execd", ["sh", "-c", "echo ready; exec sleep 300"],
                                         environment={"FROM_SPEC": "spec-value"}))
        if not started.until(b"ready", self.timeout):
            self.problems.append(f"execd: never ran (stderr {bytes(started.err)!r})")
            return
        command = self.runtime.exec(started.launch, ["sh", "-c", 'echo "$FROM_SPEC $OSMO_TASK"'],
                                    tty=False, term=None)
        with command.enter():
            done = subprocess.run(command.argv, cwd=command.cwd, env=command.env,
                                  pass_fds=command.pass_fds, capture_output=True,
                                  stdin=subprocess.DEVNULL, timeout=self.timeout, check=False)
        self.expect(done.stdout.split() == [b"spec-value", b"execd"],
                    f"execd: exec printed {done.stdout!r} (stderr {done.stderr!r}), expected "
                    "the task's variables")

    def connects(self) -> None:
        """``connector`` reaches the port the task listens on."""
        from osmo.config import free_port
        from osmo.runtime.api import ConnectError

        port = free_port(0)
        listen = " ".join(word.replace("{port}", str(port)) for word in self.listen)
        # its stdin stays open: a listener (busybox nc) may end at once on stdin's end, which
        # a pod's container (no stdin) gives it, before what is sent arrives
        started = self.start(self.launch("listener", [
            "sh", "-c", f"echo ready; sleep {int(self.timeout) + 5} | {listen}"]))
        if not started.until(b"ready", self.timeout):
            self.problems.append(f"listener: never ran (stderr {bytes(started.err)!r})")
            return
        connect = self.runtime.connector(started.launch, started.handle)
        # "ready" comes just before the listener listens, and a connection through an
        # engine's relay (the API's port-forward) is made, then ends, when nothing listens
        # yet: what was sent is sent again on a new connection until the task has it
        deadline = time.monotonic() + self.timeout
        while True:
            left = deadline - time.monotonic()
            sock, why = _retry(lambda: connect(port, False), ConnectError, max(left, 0.1))
            if sock is None:
                if not started.until(b"ping-through-the-connector", 1.0):  # a slow earlier one
                    self.problems.append(f"listener: port {port} never reached: {why}")
                return
            try:
                with sock:
                    sock.sendall(b"ping-through-the-connector\n")
            except OSError:
                pass  # ended by the relay: nothing listened yet
            if started.until(b"ping-through-the-connector", min(3.0, max(left, 0.1))):
                return
            if time.monotonic() >= deadline:
                break
        self.problems.append(f"listener: the task did not get what was sent (stdout "
                             f"{bytes(started.out)!r}, stderr {bytes(started.err)!r})")


def _retry(attempt: Callable[[], Any], error: type[Exception], timeout: float
           ) -> tuple[Any, str]:
    """``attempt()``'s result once it stops raising ``error`` (None and why: timed out)."""
    deadline, why = time.monotonic() + timeout, ""
    while time.monotonic() < deadline:
        try:
            return attempt(), ""
        except error as exc:
            why = str(exc)
            time.sleep(0.1)
    return None, why
