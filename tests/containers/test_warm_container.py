"""Warm runners inside containers (``osmo.runtime.container.warm``), with real podman.

Each test starts its own runner container (labelled with the test session's label, so
``labels`` checks none is left) and ends it with ``close``; attempts are real forks.
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.runtime.container import ContainerEngine
from osmo.runtime.container.run import ContainerRun, Mount
from osmo.runtime.container.warm import (
    ContainerWarmHandle,
    ContainerWarmKey,
    ContainerWarmRunners,
)

PATH = {"PATH": "/usr/local/bin:/usr/bin:/bin"}


@pytest.fixture
def pool(engine: ContainerEngine, labels: dict[str, str]) -> Iterator[ContainerWarmRunners]:
    runners = ContainerWarmRunners(engine, f"test-{os.getpid()}", idle=60, labels=labels)
    yield runners
    runners.close()


@pytest.fixture
def key(engine: ContainerEngine, python_image: str) -> ContainerWarmKey:
    info = engine.image(python_image)
    assert info is not None
    return ContainerWarmKey(info.id, "")


def _drain(fd: int) -> bytes:
    out = b""
    while select.select([fd], [], [], 0)[0]:
        try:
            chunk = os.read(fd, 65536)
        except BlockingIOError:
            break
        if not chunk:
            break
        out += chunk
    return out


def _finish(pool: ContainerWarmRunners, handle: ContainerWarmHandle,
            timeout: float = 60) -> tuple[int, str, str]:
    assert select.select([handle.exit_fd], [], [], timeout)[0], "the attempt did not end"
    code = pool.reap(handle)
    out, err = _drain(handle.stdout_fd), _drain(handle.stderr_fd)
    pool.release(handle)
    return code, out.decode(), err.decode()


def _python(code: str, **kw: object) -> ContainerRun:
    return ContainerRun("unused", "unused", argv=("python3", "-c", textwrap.dedent(code)),
                        env={**PATH, **kw.pop("env", {})}, **kw)  # type: ignore[arg-type]


def test_two_attempts_share_nothing(pool: ContainerWarmRunners, key: ContainerWarmKey,
                                    tmp_path: Path) -> None:
    folders = []
    for i in range(2):
        (tmp_path / f"in{i}").mkdir()
        (tmp_path / f"out{i}").mkdir()
        (tmp_path / f"in{i}" / "x.txt").write_text(f"input {i}")
        folders.append((Mount(tmp_path / f"in{i}", "/osmo/data/input/0"),
                        Mount(tmp_path / f"out{i}", "/osmo/data/output", read_only=False)))
    first = _python("""
        import os, threading, time, json
        json.dumps = 'changed'
        threading.Thread(target=time.sleep, args=(30,), daemon=True).start()
        open('/tmp/mine', 'w').write('1')
        open('/osmo/data/output/y', 'w').write('1')
        print(open('/osmo/data/input/0/x.txt').read())
        """, env={"FIRST": "1"}, mounts=folders[0])
    assert pool.ready(key)
    runner = pool.runner(key)
    code, out, err = _finish(pool, pool.start(key, first))
    assert (code, out.strip()) == (0, "input 0"), err
    second = _python("""
        import os, json, threading
        print(os.path.exists('/tmp/mine'), os.listdir('/osmo/data/output'),
              'FIRST' in os.environ, json.dumps is not None and callable(json.dumps),
              threading.active_count(), open('/osmo/data/input/0/x.txt').read())
        """, mounts=folders[1])
    code, out, err = _finish(pool, pool.start(key, second))
    assert (code, out.split()) == (0, ["False", "[]", "False", "True", "1", "input", "1"]), err
    assert (tmp_path / "out0" / "y").read_text() == "1"
    assert not list((tmp_path / "out1").iterdir())
    assert pool.runner(key) == runner


def test_an_attempt_is_enclosed(pool: ContainerWarmRunners, key: ContainerWarmKey,
                                tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    run = _python("""
        import ctypes, errno, os
        print(sorted(p for p in os.listdir('/proc') if p.isdigit()))
        try:
            open('/osmo/data/input/0/z', 'w')
        except OSError as exc:
            print(errno.errorcode[exc.errno])
        libc = ctypes.CDLL(None, use_errno=True)
        r = libc.mount(None, b'/osmo/data/input/0', None, 32 | 4096, None)
        print(r, errno.errorcode[ctypes.get_errno()])
        try:
            open('/etc/osmo-was-here', 'w')
        except OSError as exc:
            print(errno.errorcode[exc.errno])
        print([l for l in open('/proc/self/status') if l.startswith('CapEff')][0].split()[1])
        """, mounts=(Mount(tmp_path / "in", "/osmo/data/input/0"),))
    code, out, err = _finish(pool, pool.start(key, run))
    assert code == 0, err
    assert out.split("\n")[:5] == ["['1', '2']", "EROFS", "-1 EPERM", "EROFS",
                                   "0000000000000000"]


def test_segfault_and_memory_limit(pool: ContainerWarmRunners, key: ContainerWarmKey) -> None:
    code, _, _ = _finish(pool, pool.start(key, _python("import os; os.kill(os.getpid(), 11)")))
    assert code == 139
    hog = _python("b = bytearray(400 << 20); print(len(b))", memory=64 << 20)
    handle = pool.start(key, hog)
    assert handle.cgroups
    code, out, _ = _finish(pool, handle)
    assert code == 137 and not out
    assert not any(os.path.exists(group) for group in handle.cgroups)
    code, out, _ = _finish(pool, pool.start(key, _python("print('alive')")))
    assert (code, out.strip()) == (0, "alive")


def test_kill_and_force_kill(pool: ContainerWarmRunners, key: ContainerWarmKey) -> None:
    for force, expected in ((False, 143), (True, 137)):
        handle = pool.start(key, _python("import time; print('up', flush=True); "
                                         "time.sleep(300)"))
        assert select.select([handle.stdout_fd], [], [], 30)[0]
        pool.kill(handle, force=force)
        code, _, _ = _finish(pool, handle, timeout=20)
        assert code == expected


def test_credentials_stay_with_the_attempt(pool: ContainerWarmRunners, key: ContainerWarmKey,
                                           engine: ContainerEngine) -> None:
    secret = "s3cr3t-" + os.urandom(8).hex()
    run = ContainerRun("unused", "unused", argv=("python3", "-c", "import os, time; "
                                                 "print(os.environ['TOKEN'], flush=True); "
                                                 "time.sleep(300)"),
                       env=PATH, secret_env={"TOKEN": secret})
    handle = pool.start(key, run)
    assert select.select([handle.stdout_fd], [], [], 30)[0]
    assert _drain(handle.stdout_fd).strip() == secret.encode()
    name, runner = pool.runner(key) or ("", 0)
    assert secret.encode() not in Path(f"/proc/{runner}/environ").read_bytes()
    assert secret not in engine.call("inspect", name)
    pool.kill(handle, force=True)
    _finish(pool, handle)


_POOL_CHILD = """
import os, sys, time
from osmo.runtime.container import ContainerEngine, detect_engine
from osmo.runtime.container.run import ContainerRun
from osmo.runtime.container.warm import ContainerWarmKey, ContainerWarmRunners
pool = ContainerWarmRunners(ContainerEngine(detect_engine('podman')), sys.argv[2],
                            labels={sys.argv[3]: sys.argv[4]})
handle = pool.start(ContainerWarmKey(sys.argv[1], ''),
                    ContainerRun('x', 'x', argv=('sleep', '300'),
                                 env={'PATH': '/usr/local/bin:/usr/bin:/bin'}))
print(handle.pid, flush=True)
time.sleep(600)
"""


def test_kill_9_of_the_pool_ends_everything(key: ContainerWarmKey, engine: ContainerEngine,
                                            labels: dict[str, str]) -> None:
    owner = f"test-kill-{os.getpid()}"
    (label, value), = labels.items()
    root = Path(__file__).resolve().parents[2]
    child = subprocess.Popen([sys.executable, "-c", _POOL_CHILD, key.image, owner, label, value],
                             stdout=subprocess.PIPE, cwd=root,
                             env={**os.environ, "PYTHONPATH": str(root)})
    try:
        assert child.stdout is not None
        init = int(child.stdout.readline())  # the attempt's pid 1; its process: its child
        attempt = 0
        for _ in range(100):
            found = Path(f"/proc/{init}/task/{init}/children").read_text().split()
            attempt = int(found[0]) if found else 0
            if attempt and Path(f"/proc/{attempt}/cmdline").read_bytes().startswith(b"sleep"):
                break
            time.sleep(0.05)
        assert Path(f"/proc/{attempt}/cmdline").read_bytes().startswith(b"sleep")
        assert engine.containers({"osmo.owner": owner})
    finally:
        os.kill(child.pid, signal.SIGKILL)
        child.wait()
        assert child.stdout is not None
        child.stdout.close()
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline and (engine.containers({"osmo.owner": owner})
                                           or Path(f"/proc/{attempt}").exists()):
        time.sleep(0.2)
    assert not Path(f"/proc/{attempt}").exists()
    assert engine.containers({"osmo.owner": owner}) == []
