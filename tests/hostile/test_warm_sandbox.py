"""A custom type's import code under the default sandbox (issue 30), through the real CLI.

The attack a sandboxed warm start must withstand: a type's module runs code when it is
imported (once, in a warm runner, if sandboxed warm starts exist) and leaves a hook behind
(a patched ``os.fork``, called for every later fork). From there it looks for osmo's home
and for the files of another attempt. Started cold in the sandbox, its import runs inside
the attempt's own view: it sees its own attempt's folder and nothing else of the home.

A sandboxed attempt of a custom type still starts cold (``docs/how-to/warm-runners.md``):
a runner is the parent of its attempts, with their uid in the node's user namespace, so its
code reads an attempt's folders through ``/proc/PID/root`` once that attempt runs any
program (``bench/warm_sandbox_probe.py``). Only the types osmo ships start warm in the
sandbox; the tests below check that such an attempt sees what a cold one does.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import pytest

from osmo.layout import AttemptDirs
from osmo.runtime.api import Attempt, Launch
from osmo.runtime.process.sandbox import View, choose, node_network
from osmo.runtime.process.sandboxed import SandboxRuntime
from osmo.runtime.process.warm import WarmKey, WarmRunners, WarmStart
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import ResolvedType, TaskSpec
from osmo.tasktypes.registry import builtin_type
from osmo.testing.runtimes import Pipes
from osmo.worker.taskenv import base_env
from osmo.worker.workdir import prepare
from tests.conftest import Osmo, unique_sleep, wait_gone, wait_no_process, write
from tests.hostile.test_warm_runners import TYPES

SPY = r'''
import json, os
from pathlib import Path
from osmo import Param, task_type

HOME = Path(__HOME__)


def _look():
    """Every file of osmo's home this process can list, and whether it holds a secret."""
    found = {}
    for folder, _, files in os.walk(HOME):
        for name in files:
            path = os.path.join(folder, name)
            try:
                with open(path, "rb") as file:
                    found[path] = b"SECRET-" in file.read(1 << 16)
            except OSError:
                found[path] = False
    return found


AT_IMPORT = _look()
LATER = {}
_fork = os.fork


def _spying_fork():
    LATER.update(_look())
    return _fork()


os.fork = _spying_fork


@task_type(version="1", params={"mode": Param(str, default="spy")})
def spy(ctx):
    """plant: leave a secret in its folder and its output; then report what it saw."""
    work = Path(os.getcwd())
    if ctx.params["mode"] == "plant":
        (work / "planted.txt").write_text("SECRET-" + "planted")
        (ctx.output / "planted.txt").write_text("SECRET-" + "planted")
    seen = {**AT_IMPORT, **LATER, **_look()}
    (ctx.output / "seen.json").write_text(json.dumps({"mine": str(work.parent), "seen": seen,
                                                      "at_import": len(AT_IMPORT)}))
'''

PLANT = """
workflow:
  name: plant
  tasks:
  - name: plant
    type: spytypes:spy
    params: {mode: plant}
"""

LOOK = """
workflow:
  name: look
  tasks:
  - name: look
    type: spytypes:spy
"""


def _seen(osmo: Osmo, wf_id: str, task: str) -> dict:
    info = {t["name"]: t for t in osmo.query(wf_id)["tasks"]}
    return json.loads((Path(info[task]["output"]) / "seen.json").read_text())


def test_import_code_sees_only_its_own_attempt(osmo: Osmo, tmp_path: Path) -> None:
    osmo("server", "start", check=True)  # the default sandbox (bubblewrap), warm starts on
    project = tmp_path / "project"
    write(project / "spytypes.py", SPY.replace("__HOME__", repr(str(osmo.home))))
    planted = osmo.submit(write(project / "plant.yaml", PLANT), "--wait")
    looked = osmo.submit(write(project / "look.yaml", LOOK), "--wait")
    for wf, task in ((planted, "plant"), (looked, "look")):
        report = _seen(osmo, wf, task)
        mine = report["mine"].rstrip("/") + "/"
        outside = sorted(p for p in report["seen"] if not p.startswith(mine))
        assert not outside, (task, outside[:20])  # nothing of the home but its own attempt
    report = _seen(osmo, looked, "look")
    assert not any(report["seen"].values()), report  # the planted secret never reached it
    assert Path(_seen(osmo, planted, "plant")["mine"], "work", "planted.txt").exists()


# ------------------------------------------------------------------ sandboxed warm starts
# A built-in type's import code is osmo's own: its attempts start warm in the sandbox (a root
# osmo). What each attempt then sees must be what bubblewrap gives it cold. The attempts
# below are commands forked from a sandboxed runner that imports no type (the runner every
# sandboxed warm start is made from), so that a shell can probe what the attempt sees.


@dataclass
class _Node:
    runtime: SandboxRuntime
    warm: WarmRunners
    home: Path
    count: int = 0

    def launch(self, command: str, *, credentials: dict | None = None,
               secrets: dict | None = None, **typed: Any) -> Launch:
        self.count += 1
        name = f"t{self.count}"
        task = (TaskSpec(name, credentials=credentials or {}, **typed) if typed else
                TaskSpec(name, command=("sh", "-c", command), credentials=credentials or {}))
        cmd = PrepareAttempt(f"wf:{name}:0", "wf", name, 0, "pool", {}, {})
        dirs = AttemptDirs(self.home / "workflows" / "wf" / name / "0")
        made = prepare(dirs, cmd, task, base_env(os.environ), secrets or {},
                       paths=self.runtime.paths(cmd))
        return self.runtime.prepare(made, Attempt(cmd, task, dirs), progress=lambda _: None)

    def start(self, launch: Launch) -> Pipes:
        return Pipes(self.runtime.start(launch))

    def finish(self, pipes: Pipes) -> tuple[int, str, str]:
        deadline = time.monotonic() + 60
        while not pipes.ended() and time.monotonic() < deadline:
            pipes.pump(0.1)
        while pipes.pump(0):
            pass
        code = self.runtime.reap(pipes.handle)
        self.runtime.release(pipes.handle)
        return code, bytes(pipes.out).decode(), bytes(pipes.err).decode()

    def run(self, command: str, **kwargs: Any) -> tuple[int, str, str]:
        return self.finish(self.start(self.launch(command, **kwargs)))


def _started(tmp_path: Path, shares: tuple[str, ...] = ()) -> _Node:
    if os.geteuid() != 0:
        pytest.skip("sandboxed warm starts need a root osmo (a non-root one starts cold)")
    home = tmp_path / "home"
    home.mkdir(mode=0o700)
    (home / "state.db").write_text("SECRET-state")
    found = choose("on", shares)
    assert found is not None
    network = node_network(outbound=False)
    warm = WarmRunners(base_env(os.environ))
    runtime = SandboxRuntime(found.joined(network), network, hidden=(home,), warm=warm,
                             warm_commands=True)
    return _Node(runtime, warm, home)


@pytest.fixture
def node(tmp_path: Path) -> Iterator[_Node]:
    started = _started(tmp_path)
    yield started
    started.runtime.close()


def _tree(pid: int) -> list[int]:
    out = [pid]
    for task in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(OSError):
            for child in Path(f"/proc/{pid}/task/{task}/children").read_text().split():
                out += _tree(int(child))
    return out


def test_two_sandboxed_warm_attempts_in_a_row_share_nothing(node: _Node) -> None:
    dirty = ('echo leak > /tmp/leak; echo leak > /dev/shm/leak; echo "token=$TOKEN"')
    code, out, err = node.run(dirty, credentials={"api": {"TOKEN": "token"}},
                              secrets={"api": {"token": "warm-S3CRET"}})
    assert code == 0 and "token=warm-S3CRET" in out, (code, out, err)
    code, out, err = node.run('ls -a /tmp /dev/shm; echo "token=$TOKEN."')
    assert code == 0, (code, out, err)
    assert "leak" not in out and "token=." in out, out  # its own /tmp, /dev/shm, environment
    runners = node.warm.runners()
    assert [(r.type, r.started) for r in runners] == [("", 2)], runners  # one runner, twice
    for pid in _tree(runners[0].pid):  # the runner never held the attempt's credentials
        assert b"warm-S3CRET" not in Path(f"/proc/{pid}/environ").read_bytes()


def test_a_sandboxed_warm_attempt_sees_neither_home_nor_others_nor_its_runner(
        node: _Node) -> None:
    other = node.launch('echo SECRET-other > work/marker; echo ready; exec sleep 300')
    running = node.start(other)
    assert running.until(b"ready", 60), bytes(running.err)
    marker = other.cwd / "marker"
    runner = node.warm.runners()[0].pid
    probe = (f'ls /proc | grep -c "^[0-9]"; ls -a {node.home}; cat {marker} || echo unread; '
             f'kill -9 {runner} {running.handle.pid} || echo unkillable; '
             'grep -E "^(CapEff|CapBnd|NoNewPrivs|Uid):" /proc/self/status; '
             'echo mine > out.txt; mount -t tmpfs x /tmp || echo nomount; '
             '(echo x > /proc/sys/kernel/hostname) 2>/dev/null || echo rosys; '
             '(: > ../planted) 2>/dev/null || echo rofolder')
    code, out, err = node.run(probe)
    assert code == 0, (code, out, err)
    lines = out.splitlines()
    assert int(lines[0]) <= 4, out  # its init, its shell and what the shell runs
    assert "SECRET-other" not in out and "unread" in out and "unkillable" in out, out
    listed = lines[1:lines.index("unread")]
    assert sorted(listed) == [".", "..", "workflows"], out  # only the way to its own folder
    assert "CapEff:\t0000000000000000" in out and "CapBnd:\t0000000000000000" in out, out
    assert "NoNewPrivs:\t1" in out and "Uid:\t0\t0\t0\t0" in out and "nomount" in out, out
    assert "rosys" in out and "rofolder" in out, out  # /proc/sys, its folder read-only
    assert os.path.exists(f"/proc/{runner}") and not running.ended()  # both untouched
    written = next(node.home.glob("workflows/wf/*/0/work/out.txt"))
    assert written.stat().st_uid == 65534  # root inside is nobody on the host
    node.runtime.kill(running.handle, force=True)
    assert node.finish(running)[0] == 137


def test_a_sandboxed_warm_attempts_pid_1_reaps_is_out_of_reach_and_ends_the_rest(
        node: _Node) -> None:
    """Its pid 1 (the runner's child): no capability, not traceable nor signalled from inside;
    it reaps orphans, and what the task leaves running ends with the attempt."""
    mark = unique_sleep()
    probe = (f'(setsid sleep {mark} > /dev/null 2>&1 &); (sleep 0.1 &); sleep 0.5; '
             'grep -l "^State:.*Z" /proc/[0-9]*/status || echo reaped; '
             'grep -E "^(CapEff|CapPrm|CapBnd):" /proc/1/status; '
             'cat /proc/1/environ > /dev/null 2>&1 || echo sealed; '
             'kill -KILL 1; kill -STOP 1; kill -TERM 1; sleep 0.2; echo alive; exit 5')
    code, out, err = node.run(probe)
    assert code == 5 and "reaped" in out and "sealed" in out and "alive" in out, (code, out)
    assert out.count(":\t0000000000000000") == 3, out
    wait_no_process(mark, timeout=2)  # killed with its pid namespace, before the exit
    mark = unique_sleep()
    running = node.start(node.launch(f'(setsid sleep {mark} > /dev/null 2>&1 &); echo ready; '
                                      'exec sleep 300'))
    assert running.until(b"ready", 60), bytes(running.err)
    node.runtime.kill(running.handle)  # SIGTERM: the task ends, and so does its daemon
    code, _, _ = node.finish(running)
    assert code == 128 + signal.SIGTERM
    wait_no_process(mark, timeout=2)


def test_what_the_runner_shows_under_tmp_stays_shown_to_each_attempt(tmp_path: Path) -> None:
    """A share under ``/tmp`` (or osmo's own code, as in a clone under ``/tmp``) is bound
    into the view after its ``/tmp``, cold or warm; each attempt's ``/tmp`` is still its own."""
    share = tmp_path / "share"
    share.mkdir()
    (share / "data.txt").write_text("shared-data")
    node = _started(tmp_path, (f"{share}:ro",))
    try:
        code, out, err = node.run(f"cat {share}/data.txt; echo leak > /tmp/mine")
        assert (code, out) == (0, "shared-data"), (code, out, err)
        code, out, err = node.run(
            f"cat {share}/data.txt; ls /tmp; (: > {share}/w) 2>/dev/null || echo ro")
        assert code == 0 and "shared-data" in out and "mine" not in out and "ro" in out, (
            code, out, err)
        assert [(r.type, r.started) for r in node.warm.runners()] == [("", 2)]
    finally:
        node.runtime.close()


def test_only_the_types_osmo_ships_are_trusted_in_a_runner() -> None:
    """A custom or another distribution's type runs its import code cold, in its attempt."""
    assert builtin_type("sim.rollout") and builtin_type("lerobot.train")
    assert not builtin_type("spytypes:spy") and not builtin_type("osmo_plugins.sim.rollout:X")
    assert not builtin_type("no.such.type")


def test_typed_attempts_of_one_sandboxed_runner_share_nothing(tmp_path: Path) -> None:
    """What a typed attempt keeps of the one before it on a sandboxed runner: nothing.

    The runtime never imports a custom type in a runner (it starts cold: checked first);
    the node's runners are driven here with one on purpose, shown to the runner read-only,
    so that the type can probe what a typed attempt sees: its module state, threads,
    descriptors, environment and credentials, after an attempt that changed them all.
    """
    project = tmp_path / "project"
    write(project / "warmtypes.py", TYPES)
    node = _started(tmp_path, (f"{project}:ro",))
    try:
        resolved = ResolvedType("1", paths=(str(project),))
        seen = []
        for mode, env, creds in (("dirty", {"OWN": "dirty-own"}, {"api": {"TOKEN": "token"}}),
                                 ("probe", {}, {})):
            launch = node.launch("", type="warmtypes:probe", params={"mode": mode},
                                 environment=env, credentials=creds, resolved=resolved,
                                 secrets={"api": {"token": "warm-S3CRET"}})
            assert isinstance(launch.run, View), launch.run  # a custom type: cold
            key = WarmKey("warmtypes:probe", "1", (str(project),), launch.argv[0],
                          launch.env["PYTHONPATH"], sandboxed=True)
            assert node.warm.ready(key), node.warm.refused(key)
            code, out, err = node.finish(node.start(replace(launch, run=WarmStart(key,
                                                                                  launch.run))))
            assert code == 0, (code, out, err)
            seen.append(json.loads((launch.cwd.parent / "output.partial" / "seen.json")
                                   .read_text()))
        dirty, probe = seen
        assert [(r.type, r.started) for r in node.warm.runners()] == [("warmtypes:probe@1", 2)]
        assert dirty["secret"] == "warm-S3CRET" and dirty["own"] == "dirty-own"
        assert dirty["leaked"] == "1" and dirty["touched"] and dirty["patched"]
        assert probe["secret"] is None and probe["own"] is None, probe
        assert probe["leaked"] is None and not probe["touched"] and not probe["patched"], probe
        assert probe["threads"] == 1, probe
        assert not any("held.txt" in fd for fd in probe["fds"]), probe["fds"]
        assert probe["ppid"] == 1 and probe["pid"] == 2, probe  # its own pid namespace
    finally:
        node.runtime.close()


POOL = r"""
import json, sys, time
from pathlib import Path
from tests.hostile.test_warm_sandbox import _started

node = _started(Path(sys.argv[1]))
pipes = node.start(node.launch("echo ready; exec sleep " + sys.argv[2]))
assert pipes.until(b"ready", 60), bytes(pipes.err)
print(json.dumps({"attempt": pipes.handle.pid, "runner": node.warm.runners()[0].pid}),
      flush=True)
time.sleep(600)
"""


def test_kill_9_of_the_pool_ends_its_sandboxed_runner_and_attempts(tmp_path: Path) -> None:
    """Nothing of a sandboxed runner outlives the process that started it (its pool)."""
    if os.geteuid() != 0:
        pytest.skip("sandboxed warm starts need a root osmo (a non-root one starts cold)")
    mark = unique_sleep()
    pool = subprocess.Popen([sys.executable, "-c", POOL, str(tmp_path), mark],
                            cwd=Path(__file__).parents[2], stdout=subprocess.PIPE)
    try:
        assert pool.stdout is not None
        pids = json.loads(pool.stdout.readline())
        with pytest.raises(AssertionError):  # the attempt's sleep runs
            wait_no_process(mark, timeout=0.5)
        os.kill(pool.pid, signal.SIGKILL)
        pool.wait()
        wait_gone(pids["runner"])
        wait_gone(pids["attempt"])
        wait_no_process(mark)
    finally:
        if pool.poll() is None:
            pool.kill()
            pool.wait()
        if pool.stdout is not None:
            pool.stdout.close()

