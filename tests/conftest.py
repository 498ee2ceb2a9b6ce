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
import time
from collections.abc import Generator, Iterator
from dataclasses import dataclass
from pathlib import Path

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

    def __call__(self, *args: str, timeout: float = 180, check: bool = False,
                 cwd: Path = REPO) -> Result:
        proc = subprocess.run([sys.executable, "-m", "osmo", *args], env=self.env,
                              capture_output=True, text=True, timeout=timeout, cwd=cwd)
        result = Result(proc.returncode, proc.stdout, proc.stderr)
        if check and result.code != 0:
            raise AssertionError(f"osmo {' '.join(args)} exited {result.code}\n"
                                 f"stdout:\n{result.out}\nstderr:\n{result.err}")
        return result

    def submit(self, spec: Path | str, *args: str) -> str:
        """Submit and return the workflow id (asserts success)."""
        r = self("submit", str(spec), *args, check=True)
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


def read_pid(path: Path, timeout: float = 60) -> int:
    """Wait for a task to write its pid (``echo $$ > FILE``) and return it."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            text = path.read_text()
        except FileNotFoundError:
            text = ""
        if text.endswith("\n"):
            return int(text)
        if time.monotonic() > deadline:
            raise AssertionError(f"no pid was written to {path}")
        time.sleep(0.02)


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
    runner("server", "start", check=True)
    yield runner
    runner.stop_server()
