"""The bubblewrap sandbox with real processes: what a command sees, signals, exit codes, choice."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import socket
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.errors import InfrastructureError, UsageError
from osmo.runtime import ProcessGroups, StartError
from osmo.runtime.process import sandbox as sandbox_mod
from osmo.runtime.process.netns import Entry, NodeNetwork
from osmo.runtime.process.sandbox import Sandbox, View, choose, node_network
from tests.runtime.churn import churning_mounts
from tests.runtime.test_process_runtime import read_all, wait_exit, wait_until

ENV = {"PATH": os.environ["PATH"]}


@pytest.fixture(scope="module")
def network() -> Iterator[NodeNetwork]:
    """A node's namespaces, as a pool makes them."""
    made = node_network()
    yield made
    made.close()


@pytest.fixture
def box(network: NodeNetwork) -> Sandbox:
    found = choose("on")  # ./dev test installs bubblewrap; CI runs with it
    assert found is not None
    return found.joined(network)


@pytest.fixture
def home(tmp_path: Path, box: Sandbox) -> Path:
    """An osmo-like home: a secret beside one attempt's folders, and another attempt.

    Its writable folders are the task's, as a pool makes them (``sandboxed.hand_over``).
    """
    root = tmp_path / "home"
    for folder in ("a/work", "a/output.partial", "a/files", "other/work", "input"):
        (root / folder).mkdir(parents=True)
    (root / "state.db").write_text("secret")
    (root / "other" / "work" / "note").write_text("other's")
    (root / "input" / "data.txt").write_text("input")
    if box.owner is not None:
        for folder in ("a/work", "a/output.partial", "a/files"):
            os.chown(root / folder, *box.owner)
    return root


def view(home: Path) -> View:
    a = home / "a"
    return View(hidden=(home,), readonly=(a, home / "input"),
                writable=(a / "work", a / "output.partial", a / "files"), cwd=a / "work")


def run(box: Sandbox, home: Path, script: str) -> tuple[int, str]:
    runtime = ProcessGroups(box)
    handle = runtime.start(["sh", "-c", script], cwd=home / "a" / "work", env=ENV,
                           view=view(home))
    try:
        out = read_all(handle.stdout_fd).decode()
        wait_exit(handle)
        return runtime.reap(handle), out
    finally:
        runtime.release(handle)


def test_command_sees_only_its_own_folders(box: Sandbox, home: Path) -> None:
    a = home / "a"
    code, out = run(box, home, f"""
        pwd; ls -a {home}; cat {home}/state.db || echo no-db; cat {home}/other/work/note || echo no-other
        echo made > {a}/output.partial/o && echo wrote-output
        echo x > {a}/work/w && echo wrote-work
        echo x > {a}/task.json || echo ro-folder
        echo x > {home}/input/data.txt || echo ro-input
        touch /usr/evil || echo ro-host
        echo x > {home.parent}/shared  # the private /tmp's copy of the path, if any
        exit 3""")
    lines = out.split()
    assert code == 3
    assert lines[0] == str(a / "work")
    assert "state.db" not in lines and "other" not in out.split("no-db")[0]
    for word in ("no-db", "no-other", "wrote-output", "wrote-work", "ro-folder", "ro-input",
                 "ro-host"):
        assert word in lines, (word, out)
    assert (a / "output.partial" / "o").read_text() == "made\n"
    assert (home / "state.db").read_text() == "secret"
    assert not (home / "a" / "task.json").exists()
    assert not (home.parent / "shared").exists()  # the host's /tmp is not the task's


def test_tmp_is_the_tasks_own(box: Sandbox, home: Path) -> None:
    name = f"/tmp/osmo-private-{os.getpid()}-{id(home)}"
    (home.parent / "planted").write_text("host")
    code, out = run(box, home, f"echo x > {name} && cat {name}; ls {home.parent / 'planted'}")
    assert code != 0 and out == "x\n"  # written in its own /tmp; the host's is not there
    assert not os.path.exists(name)


def test_a_shared_folder_is_writable_and_the_home_inside_it_stays_hidden(
        box: Sandbox, home: Path, network: NodeNetwork) -> None:
    shared = choose("on", [home.parent])
    assert shared is not None and shared.shared == (os.path.realpath(home.parent),)
    code, out = run(shared.joined(network), home, f"""
        echo x > {home.parent}/note && echo wrote-shared
        cat {home}/state.db || echo no-db""")
    assert code == 0 and out.split() == ["wrote-shared", "no-db"], out
    assert (home.parent / "note").read_text() == "x\n"


def test_a_relative_shared_folder_is_refused() -> None:
    with pytest.raises(UsageError, match="absolute"):
        choose("on", ["scratch"])


def test_command_has_its_own_pids(box: Sandbox, home: Path) -> None:
    code, out = run(box, home, "echo $$; ls /proc | grep -c '^[0-9]'")
    pid, count = out.split()
    assert code == 0 and int(pid) <= 3 and int(count) <= 4, out  # bwrap, sh, ls (and grep)


@pytest.mark.parametrize(("script", "code"), [("exit 0", 0), ("exit 42", 42),
                                               ("kill -USR1 $$", 128 + signal.SIGUSR1)])
def test_exit_codes_are_the_commands_own(box: Sandbox, home: Path, script: str,
                                         code: int) -> None:
    assert run(box, home, script)[0] == code


def test_sigterm_reaches_the_command_and_grace_is_kept(box: Sandbox, home: Path) -> None:
    """A SIGTERM must not kill bwrap (that would SIGKILL the sandbox at once)."""
    runtime = ProcessGroups(box)
    out = home / "a" / "output.partial"
    handle = runtime.start(
        ["sh", "-c", f"trap 'echo term > {out}/t; exit 7' TERM; touch {out}/ready; "
                     "while :; do sleep 0.05; done"],
        cwd=home / "a" / "work", env=ENV, view=view(home))
    try:
        wait_until(lambda: (out / "ready").exists())
        runtime.kill(handle)
        wait_exit(handle)
        assert runtime.reap(handle) == 7
        assert (out / "t").read_text() == "term\n"
    finally:
        runtime.release(handle)


def test_missing_command_fails_the_start(box: Sandbox, home: Path) -> None:
    runtime = ProcessGroups(box)
    with pytest.raises(StartError, match="command not found: 'no-such-cmd-x'"):
        runtime.start(["no-such-cmd-x"], cwd=home / "a" / "work", env=ENV, view=view(home))


def test_choose_modes(monkeypatch: pytest.MonkeyPatch) -> None:
    assert choose("off") is None
    with pytest.raises(UsageError, match="choose one of auto, on, off"):
        choose("sometimes")  # type: ignore[arg-type]
    sandbox_mod._probe_result.cache_clear()
    monkeypatch.setenv("PATH", "/nonexistent")
    try:
        assert choose("auto") is None
        with pytest.raises(InfrastructureError, match="install the 'bubblewrap' package"):
            choose("on")
    finally:
        monkeypatch.undo()
        sandbox_mod._probe_result.cache_clear()


def test_argv_orders_mounts_parents_first(home: Path) -> None:
    argv = Sandbox("bwrap", entry=Entry()).argv(["true"], view(home))
    real = os.path.realpath
    assert argv.index(real(home)) < argv.index(real(home / "a")) < argv.index(
        real(home / "a" / "work"))
    assert argv[argv.index(real(home / "a")) - 1] == "--ro-bind-try"
    assert argv[argv.index(real(home / "a" / "work")) - 1] == "--bind-try"
    assert "--die-with-parent" in argv and "--unshare-pid" in argv
    assert argv[-2:] == ["--", "true"]


def test_osmos_own_folders_under_tmp_stay_visible_read_only(box: Sandbox, home: Path,
                                                            tmp_path: Path) -> None:
    """A clone or a virtualenv under /tmp: the sandbox's own /tmp must not hide it."""
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    (venv / "bin" / "tool").write_text("#!/bin/sh\necho from-the-venv\n")
    (venv / "bin" / "tool").chmod(0o755)
    nested, outside = venv / "lib", Path("/usr")
    nested.mkdir()
    found = sandbox_mod.runtime_folders([str(venv), str(nested), str(outside), "relative", ""])
    assert found == (os.path.realpath(venv),)
    runtime = dataclasses.replace(box, runtime=found)
    code, out = run(runtime, home, f"{venv}/bin/tool; touch {venv}/x || echo read-only")
    assert code == 0 and out.split() == ["from-the-venv", "read-only"], out
    code, out = run(box, home, f"{venv}/bin/tool || echo hidden")
    assert out.split()[-1] == "hidden"  # without it, the task's own /tmp hides the venv


def test_a_sandbox_that_cannot_be_set_up_for_a_moment_is_still_found_by_the_probe() -> None:
    """A server started while mounts come and go probes bubblewrap under the same race: a
    probe that loses it once must not leave the server without a sandbox, or without the
    status pipe that tells a setup failure from the command's exit 1."""
    with churning_mounts():
        for _ in range(15):
            sandbox_mod._probe_result.cache_clear()
            try:
                found, why, _ = sandbox_mod._probe_result()
            finally:
                sandbox_mod._probe_result.cache_clear()
            assert found is not None, why
            assert found.status


def test_a_sandbox_that_cannot_be_set_up_is_told_from_the_commands_exit(
        box: Sandbox, home: Path) -> None:
    """A mount vanishing under bwrap's setup fails it with exit 1: never the command's own.

    The command is ``false`` (exit 1 too): a start whose sandbox failed is marked
    ``setup_failed`` (bwrap's message on its stderr), one whose command ran never is.
    """
    runtime = ProcessGroups(box)
    seen = {"ran": 0, "setup failed": 0}
    with churning_mounts():
        for _ in range(400):  # until both were seen a few times (usually about 30 starts)
            if min(seen.values()) >= 3:
                break
            handle = runtime.start(["false"], cwd=home / "a" / "work", env=ENV,
                                   view=view(home))
            try:
                err = read_all(handle.stderr_fd).decode()
                wait_exit(handle)
                code = runtime.reap(handle)
            finally:
                runtime.release(handle)
            if handle.setup_failed:
                assert err.startswith("bwrap: "), err
                seen["setup failed"] += 1
            else:
                assert (code, err) == (1, ""), err
                seen["ran"] += 1
    assert seen["setup failed"] > 0 and seen["ran"] > 0, seen  # the race did happen


def test_a_home_reached_through_a_symlink_is_hidden_at_its_real_path(
        box: Sandbox, home: Path, tmp_path: Path) -> None:
    """The sandbox resolves osmo's home once; what it binds below it is at the real path."""
    link = tmp_path / "link"
    link.symlink_to(home)
    a = link / "a"
    linked = View(hidden=(link,), readonly=(a, link / "input"),
                  writable=(a / "work", a / "output.partial", a / "files"), cwd=a / "work")
    argv = box.argv(["true"], linked)
    assert argv[argv.index("--tmpfs", argv.index("/tmp") + 1) + 1] == os.path.realpath(home)
    assert os.path.realpath(home / "a" / "work") in argv and str(a / "work") not in argv
    runtime = ProcessGroups(box)
    handle = runtime.start(["sh", "-c", f"""
        pwd; cat {home}/state.db || echo no-db
        echo x > {home}/a/output.partial/o && echo wrote-output
        echo x > {home}/a/task.json || echo ro-folder"""], cwd=a / "work", env=ENV, view=linked)
    try:
        out = read_all(handle.stdout_fd).decode()
        wait_exit(handle)
        assert runtime.reap(handle) == 0, out
    finally:
        runtime.release(handle)
    assert out.split() == [os.path.realpath(home / "a" / "work"), "no-db", "wrote-output",
                           "ro-folder"], out
    assert (home / "a" / "output.partial" / "o").read_text() == "x\n"


def test_a_task_cannot_undo_its_mounts(box: Sandbox, home: Path) -> None:
    """Whatever uid the worker runs as (root too), a task holds no capability to unmount the
    tmpfs that hides osmo's home, remount the host writable, or mount anything of its own."""
    code, out = run(box, home, f"""
        umount {home} 2>/dev/null; umount -l {home} 2>/dev/null
        cat {home}/state.db 2>/dev/null || echo no-db
        mount -o remount,rw / 2>/dev/null; touch /usr/osmo-evil-{os.getpid()} 2>/dev/null \
            || echo ro-host
        mount -t tmpfs none {home}/a/work 2>/dev/null || echo no-mount
        grep '^CapEff' /proc/self/status""")
    assert code == 0, out
    assert out.split()[:3] == ["no-db", "ro-host", "no-mount"], out
    assert out.split()[-1] == "0000000000000000", out
    assert not os.path.exists(f"/usr/osmo-evil-{os.getpid()}")


UNPRIVILEGED = r"""
import json, os, select, socket, sys
from pathlib import Path
from osmo.runtime import ProcessGroups
from osmo.runtime.process.sandbox import View, choose, node_network
home, port = Path(sys.argv[1]), int(sys.argv[2])
work = home / "a" / "work"
work.mkdir(parents=True)
(home / "state.db").write_text("secret")
net = node_network()
try:
    runtime = ProcessGroups(choose("on").joined(net))
    view = View(hidden=(home,), readonly=(home / "a",), writable=(work,), cwd=work)
    handle = runtime.start(["sh", "-c", f'''
        id -u; grep CapBnd /proc/self/status | cut -f2; readlink /proc/self/ns/net
        cat {home}/state.db 2>/dev/null || echo no-db
        echo made > made && echo wrote
        python3 -c "import socket; socket.create_connection(('127.0.0.1', {port}), 2)" \
            2>/dev/null && echo reached || echo unreachable'''],
        cwd=work, env={"PATH": "/usr/bin:/bin"}, view=view)
    select.select([handle.exit_fd], [], [])
    code = runtime.reap(handle)
    out = os.read(handle.stdout_fd, 65536).decode().split()
    runtime.release(handle)
finally:
    net.close()
print(json.dumps({"code": code, "out": out, "caveat": net.caveat,
                  "made": (work / "made").stat().st_uid}))
"""


def test_the_sandbox_of_a_user_that_is_not_root(tmp_path: Path) -> None:
    """osmo run by an ordinary user (here nobody, from a root test run): the node's
    namespaces are entered through nsenter; the task is root only inside, writes its files
    as that user, sees a network of its own, and no capability is left."""
    where = Path(tempfile.mkdtemp(prefix="osmo-user-"))  # a folder nobody can reach
    try:
        where.chmod(0o755)
        shutil.copytree(Path(__file__).resolve().parents[2] / "osmo", where / "osmo")
        (where / "home").mkdir(mode=0o777)
        (where / "home").chmod(0o777)
        with socket.socket() as listener:
            listener.bind(("127.0.0.1", 0))
            listener.listen()
            port = listener.getsockname()[1]
            command = ["/usr/bin/python3", "-c", UNPRIVILEGED, str(where / "home"), str(port)]
            if os.geteuid() == 0:
                command = ["setpriv", "--reuid=nobody", "--regid=nogroup", "--clear-groups",
                           *command]
            done = subprocess.run(command, capture_output=True, text=True, timeout=60,
                                  env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(where)},
                                  cwd=where, check=False)
        assert done.returncode == 0, done.stderr
        result = json.loads(done.stdout)
        uid, bounding, netns, *rest = result["out"]
        assert result["code"] == 0, result
        assert (uid, bounding) == ("0", "0000000000000000"), result
        assert netns != os.readlink("/proc/self/ns/net"), result
        assert rest == ["no-db", "wrote", "unreachable"], result
        assert result["made"] == (65534 if os.geteuid() == 0 else os.geteuid())
    finally:
        shutil.rmtree(where, ignore_errors=True)
