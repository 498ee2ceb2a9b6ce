"""Shared fixtures: an isolated OSMO_HOME with a real server process, and a CLI runner.

Servers are started through the real CLI (``osmo server start``) on loopback with a free
port, and stopped by PID at the end (never by name).

A full run must not skip silently: with ``OSMO_NO_SKIPS=1`` (``./dev test`` sets it) every
skip — of a test, or of a whole module at collection — becomes a failure, unless it matches
an entry of :data:`ALLOWED_SKIPS`, each of which says why it may skip. (An expected failure,
``xfail``, is not a skip.)
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import pytest

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class AllowedSkip:
    """A skip a full run may take: tests whose id starts with ``test_id`` skipping for a
    reason that matches ``reason`` (a regex), while ``when`` holds."""

    test_id: str
    reason: str
    when: bool = True


ALLOWED_SKIPS: tuple[AllowedSkip, ...] = (
    # lerobot >= 0.5 (the `learn` extra) installs only on Python >= 3.12. `./dev test` falls
    # back to an older python3 when 3.12 is missing, and says loudly that the learning tasks
    # will not run; on 3.12 these skips are failures like any other.
    AllowedSkip("tests/plugins/test_learn.py", r"lerobot", when=sys.version_info < (3, 12)),
    AllowedSkip("tests/e2e/test_pipeline.py", r"lerobot", when=sys.version_info < (3, 12)),
    # Reproducing bubblewrap's setup race makes and removes mounts (tests/runtime/churn.py),
    # which only root can, as does a shared mount slirp4netns must leave alone; the rest of
    # the sandbox's tests run as any user.
    *(AllowedSkip(test, r"needs root", when=os.geteuid() != 0) for test in (
        "tests/runtime/test_sandbox.py::test_a_sandbox_that_cannot_be_set_up",  # both tests
        "tests/worker/test_pool_sandbox.py::test_a_setup_that_fails_for_a_moment",
        "tests/e2e/test_sandbox_setup.py",
        "tests/runtime/test_netns.py::test_starting_a_node_network_unmounts_nothing")),
    # The Slurm test cluster runs its daemons as root and each node in a pid namespace of its
    # own (tests/slurm/cluster.py); Slurm's packages themselves must be there (./dev test).
    AllowedSkip("tests/slurm/", r"needs root", when=os.geteuid() != 0),
)


def _skip_allowed(test_id: str, reason: str) -> bool:
    return any(a.when and test_id.startswith(a.test_id) and re.search(a.reason, reason)
               for a in ALLOWED_SKIPS)


_FORBIDDEN_SKIPS: list[str] = []  # skipped modules (collection), reported at the end


def _forbidden_skip(report: pytest.CollectReport | pytest.TestReport) -> str | None:
    """Why ``report`` is a skip a full run may not take (None: it is not one)."""
    if (os.environ.get("OSMO_NO_SKIPS") != "1" or not report.skipped
            or hasattr(report, "wasxfail")):
        return None
    longrepr = report.longrepr
    reason = longrepr[2] if isinstance(longrepr, tuple) else str(longrepr)
    if _skip_allowed(report.nodeid, reason):
        return None
    return (f"{report.nodeid}: {reason}\nOSMO_NO_SKIPS=1 (./dev test): a full run may not "
            "skip this. Provide what it needs, or add it to ALLOWED_SKIPS in "
            "tests/conftest.py with the reason it may skip.")


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]
                              ) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    report = yield
    why = _forbidden_skip(report)
    if why is not None:  # the test is reported as failed, with the reason
        report.outcome = "failed"
        report.longrepr = why
    return report


@pytest.hookimpl(wrapper=True)
def pytest_make_collect_report(collector: pytest.Collector
                               ) -> Generator[None, pytest.CollectReport, pytest.CollectReport]:
    report = yield
    why = _forbidden_skip(report)
    if why is not None:  # a collection error would stop the whole run: fail it at the end
        _FORBIDDEN_SKIPS.append(why)
    return report


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    if _FORBIDDEN_SKIPS:
        terminalreporter.section("skipped modules (not allowed in a full run)", red=True)
        for why in _FORBIDDEN_SKIPS:
            terminalreporter.line(why)


def pytest_sessionfinish(session: pytest.Session) -> None:
    if _FORBIDDEN_SKIPS and session.exitstatus in (pytest.ExitCode.OK,
                                                    pytest.ExitCode.NO_TESTS_COLLECTED):
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


@dataclass
class Result:
    """A finished CLI run."""

    code: int
    out: str
    err: str

    def json(self) -> object:
        return json.loads(self.out)


class Osmo:
    """Runs the real ``osmo`` CLI against one OSMO_HOME."""

    def __init__(self, home: Path) -> None:
        self.home = home
        self.env = dict(os.environ, OSMO_HOME=str(home), PYTHONUNBUFFERED="1")
        self.env.pop("OSMO_SERVER", None)
        self.env.setdefault("OSMO_RUNTIME", "process")  # image tasks: tests/containers
        # Tests hand gate and marker files to tasks through their tmp folder: shared with the
        # sandbox explicitly (a sandboxed task has its own empty /tmp otherwise), and open to
        # the tasks' uid (a root server's are nobody: osmo.runtime.process.sandbox).
        self.env.setdefault("OSMO_SANDBOX_SHARE", str(home.parent))
        if home.parent.is_dir() and home.parent != Path(tempfile.gettempdir()):
            home.parent.chmod(0o1777)

    def __call__(self, *args: str, timeout: float = 180, check: bool = False,
                 cwd: Path = REPO) -> Result:
        proc = subprocess.run([sys.executable, "-m", "osmo", *args], env=self.env,
                              capture_output=True, text=True, timeout=timeout, cwd=cwd)
        result = Result(proc.returncode, proc.stdout, proc.stderr)
        if check and result.code != 0:
            raise AssertionError(f"osmo {' '.join(args)} exited {result.code}\n"
                                 f"stdout:\n{result.out}\nstderr:\n{result.err}")
        return result

    def submit(self, spec: Path | str, *args: str, timeout: float = 180) -> str:
        """Submit and return the workflow id (asserts success)."""
        r = self("submit", str(spec), *args, check=True, timeout=timeout)
        line = [ln for ln in r.out.splitlines() if ln.startswith("Workflow ID - ")][0]
        return line.split(" - ", 1)[1].strip()

    def query(self, wf_id: str) -> dict:
        return self("query", wf_id, "--format", "json", check=True).json()  # type: ignore[return-value]

    def wait_for(self, wf_id: str, predicate, timeout: float = 120) -> dict:  # type: ignore[no-untyped-def]
        """Re-query until ``predicate(info)`` holds (event waits are in the SDK; this is a test)."""
        deadline = time.monotonic() + timeout
        while True:
            info = self.query(wf_id)
            if predicate(info):
                return info
            if time.monotonic() > deadline:
                raise AssertionError(f"condition not reached; last state: {info}")
            time.sleep(0.1)

    def server_pid(self) -> int | None:
        try:
            return int(json.loads((self.home / "server.json").read_text())["pid"])
        except (OSError, ValueError, KeyError):
            return None

    def stop_server(self) -> None:
        """Stop this home's server by PID (SIGTERM, then SIGKILL)."""
        pid = self.server_pid()
        if pid is None:
            return
        try:
            os.kill(pid, signal.SIGTERM)
        except ProcessLookupError:
            return
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                return
            time.sleep(0.05)
        os.kill(pid, signal.SIGKILL)


def write(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` (creating parents) and return the path."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def ended(info: dict) -> bool:
    """Whether a workflow (``osmo query --format json``) has reached a final status."""
    return info["status"] not in ("PENDING", "RUNNING", "WAITING")


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie (an exited child nobody reaped yet,
    such as an orphan in a container whose init does not reap)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def wait_gone(pid: int, timeout: float = 15) -> float:
    """Wait until process ``pid`` is gone; return when (``time.monotonic()``)."""
    deadline = time.monotonic() + timeout
    while process_alive(pid):
        if time.monotonic() > deadline:
            raise AssertionError(f"process {pid} is still alive after {timeout}s")
        time.sleep(0.02)
    return time.monotonic()


T = TypeVar("T")


def retry_oserror(fn: Callable[[], T], timeout: float = 30) -> T:
    """``fn()`` once it stops raising OSError (a task's server may still be starting)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return fn()
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def unique_sleep() -> str:
    """A ``sleep`` argument no other process has (600 s and a bit): a task's processes are
    then found by it (:func:`wait_no_process`), where a sandboxed ``$$`` means nothing."""
    return f"600.{os.getpid()}{time.monotonic_ns() % 10**9:09d}"


def wait_no_process(arg: str, timeout: float = 15) -> None:
    """Wait until no live process has ``arg`` as one of its arguments."""
    deadline = time.monotonic() + timeout
    while True:
        left = []
        for name in os.listdir("/proc"):
            try:
                if name.isdigit() and arg.encode() in Path(
                        f"/proc/{name}/cmdline").read_bytes().split(b"\0"):
                    left.append(int(name))
            except OSError:
                pass
        if not [pid for pid in left if process_alive(pid)]:
            return
        if time.monotonic() > deadline:
            raise AssertionError(f"processes {left} ({arg}) still alive after {timeout}s")
        time.sleep(0.02)


def host_pid(task_pid: int, marker: str) -> int | None:
    """The pid on this host of a task's process whose own pid is ``task_pid``.

    A sandboxed task has its own pid namespace, so the ``$$`` it writes is not a pid here:
    its process is the one whose ``NSpid`` (``/proc/<pid>/status``) ends with ``task_pid``
    and whose environment holds ``marker`` (the test's folder: its osmo homes, hence
    ``OSMO_OUTPUT``, lie there). Unsandboxed, ``task_pid`` itself (its environment holds the
    marker too). None: no such process.
    """
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            status = Path(f"/proc/{name}/status").read_text()
            nspid = [line.split()[1:] for line in status.splitlines()
                     if line.startswith("NSpid:")][0]
            if int(nspid[-1]) != task_pid or marker.encode() not in Path(
                    f"/proc/{name}/environ").read_bytes():
                continue
        except (OSError, IndexError, ValueError):
            continue
        return int(name)
    return None


def read_pid(path: Path, timeout: float = 60) -> int:
    """Wait for a task to write its pid (``echo $$ > FILE``); return its pid on this host.

    (Mapped by :func:`host_pid`, with the pid file's folder as the marker.)
    """
    deadline = time.monotonic() + timeout
    while True:
        try:
            text = path.read_text()
        except FileNotFoundError:
            text = ""
        if text.endswith("\n"):
            pid = host_pid(int(text), str(path.parent))
            if pid is not None:
                return pid
        if time.monotonic() > deadline:
            raise AssertionError(f"no pid was written to {path}")
        time.sleep(0.02)


@pytest.fixture
def tmp_path(tmp_path: Path) -> Path:
    """pytest's ``tmp_path``, which any user may enter and add to (mode 1777).

    Tests share it with their tasks (``Osmo``), and a root server's sandboxed tasks are
    ``nobody`` on the host (``osmo.runtime.process.sandbox``): pytest's 0700 would shut them out.
    """
    tmp_path.chmod(0o1777)
    return tmp_path


@pytest.fixture
def osmo(tmp_path: Path) -> Iterator[Osmo]:
    """A CLI bound to a fresh OSMO_HOME; its server (auto-started on use) is stopped after."""
    runner = Osmo(tmp_path / "home")
    yield runner
    runner.stop_server()


@pytest.fixture(scope="module")
def shared_osmo(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Osmo]:
    """One server shared by a test module (for tests that do not kill it)."""
    runner = Osmo(tmp_path_factory.mktemp("osmo") / "home")
    # its tasks use each test's tmp_path: share the session's base folder with them
    runner.env["OSMO_SANDBOX_SHARE"] = str(tmp_path_factory.getbasetemp())
    tmp_path_factory.getbasetemp().chmod(0o755)  # (each tmp_path is then 1777: tmp_path)
    runner("server", "start", check=True)
    yield runner
    runner.stop_server()
