"""Probe (issue 30): can a warm runner inside a running container give each attempt its own view?

Not used by osmo: it tries, as root with podman, the parts a container warm start would be
built from, prints one line per step (``ok`` or the errno), and times an attempt against
``podman run --rm`` and ``podman exec`` of the same image.

The runner is a long-lived container of the image (``podman run -d``, the engine's defaults:
no ``CAP_SYS_ADMIN``, podman's masks on ``/proc``), running this file with ``--inside``. Its
only link to the pool is a folder bound at ``/osmo-relay`` holding the pool's Unix socket.
For each attempt the pool makes the attempt's folders on the host and sends detached clones
of them (``open_tree(OPEN_TREE_CLONE)``, the input read-only) with ``SCM_RIGHTS``, as the
sandboxed warm start does (``osmo.runtime.process.mounts``). The runner forks; the child:

- unshares a user namespace (mapping only its own root) with a mount, pid, IPC and UTS
  namespace: the container's root has no ``CAP_SYS_ADMIN``, its own user namespace gives it
  one over these namespaces only;
- makes its mounts private, moves the attempt's folders to ``/osmo/data/{input,output}``,
  mounts an empty ``/tmp`` and an empty tmpfs over ``/osmo-relay`` (after connecting to the
  pool: the attempt keeps one connection, never the folder);
- forks its pid 1, which needs a ``/proc`` of the new pid namespace. ``mount("proc")`` is
  refused in the container (podman's covers on ``/proc``: no ``/proc`` is fully visible).
  The sandbox's way: pid 1 makes the proc context (``fsopen``), the pool ``fsmount`` s it on
  the host and sends the mount back, pid 1 moves it on ``/proc`` and binds ``/proc/sys``
  read-only;
- drops every capability (``no_new_privs``), then runs the checks an attack would try: what
  it sees of ``/osmo-relay``, the pids in ``/proc``, unmounting the covers (refused), and
  a nested user namespace that would uncover them (the covers are locked there).

Usage (as root, from the repository):
  python bench/container_warm_probe.py [--image localhost/osmo:test] [--attempts 20]
The image needs ``python3`` (3.11+); the repository is bound read-only and put first on its
``PYTHONPATH``. ``CONTAINERS_CONF`` is honoured (this machine needs runc and no default
ulimits: see FACTS.md); without it one is written to a temporary folder.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RELAY = "/osmo-relay"
CONF = '[containers]\ndefault_ulimits = []\n\n[engine]\nruntime = "runc"\n'


# ------------------------------------------------------------------- inside the container

def _step(report: dict[str, str], name: str, action: object) -> bool:
    try:
        result = action() if callable(action) else action
    except OSError as exc:
        report[name] = f"FAILED ({exc})"
        return False
    report[name] = "ok" if result in (None, 0, True) else f"ok ({result})"
    return True


def _map_root() -> None:
    """In a new user namespace: its uid 0 and gid 0 are the container's root, nothing else."""
    Path("/proc/self/setgroups").write_text("deny")
    Path("/proc/self/uid_map").write_text("0 0 1")
    Path("/proc/self/gid_map").write_text("0 0 1")


def _attempt(index: int, fds: list[int], started: float) -> None:
    """The forked child: become the attempt, report what it sees; never returns."""
    from osmo.runtime.process import mounts

    report: dict[str, str] = {"attempt": str(index)}
    code = 1
    try:
        pool = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        pool.connect(f"{RELAY}/pool.sock")
        ok = _step(report, "unshare user+mount+pid+ipc+uts", lambda: mounts.unshare(
            0x10000000 | mounts.NEWNS | mounts.NEWPID | mounts.NEWIPC | mounts.NEWUTS))
        ok = ok and _step(report, "map root to the container's root", _map_root)
        ok = ok and _step(report, "mounts private", mounts.make_private)
        ok = ok and _step(report, "move input (read-only clone)",
                          lambda: mounts.move(fds[0], "/osmo/data/input"))
        ok = ok and _step(report, "move output (writable clone)",
                          lambda: mounts.move(fds[1], "/osmo/data/output"))
        ok = ok and _step(report, "empty /tmp", lambda: mounts.mount_tmpfs("/tmp", 0o1777))
        ok = ok and _step(report, "cover /osmo-relay",
                          lambda: mounts.mount_tmpfs(RELAY, 0o755))
        if not ok:
            raise OSError("a step failed")
        init = os.fork()
        if init == 0:
            os._exit(_init(pool, report, started))
        pool.close()
        code = os.waitstatus_to_exitcode(os.waitpid(init, 0)[1])
    except BaseException as exc:  # noqa: BLE001 - a probe: report and exit
        report["error"] = repr(exc)
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as late:
            late.connect(f"{RELAY}/pool.sock")
            late.sendall(json.dumps(report).encode())
    os._exit(code)


def _init(pool: socket.socket, report: dict[str, str], started: float) -> int:
    """pid 1 of the attempt: /proc through the pool, every capability dropped, the checks."""
    from osmo.runtime.process import mounts

    _step(report, "mount proc in the container (expected: refused)",
          lambda: mounts._mount("proc", "/proc", "proc", 0))
    context = mounts.proc_context()
    socket.send_fds(pool, [b"proc"], [context])
    _, got, _, _ = socket.recv_fds(pool, 16, 1)
    ok = bool(got) and _step(report, "/proc from the pool's fsmount",
                             lambda: mounts.move(got[0], "/proc"))
    ok = ok and _step(report, "/proc/sys read-only",
                      lambda: mounts.bind("/proc/sys", "/proc/sys", readonly=True))
    ok = ok and _step(report, "drop every capability", mounts.drop_privileges)
    report["start_ms"] = f"{(time.perf_counter() - started) * 1000:.2f}"
    if ok:
        report["pid"] = str(os.getpid())
        report["pids in /proc"] = " ".join(sorted(p for p in os.listdir("/proc") if p.isdigit()))
        report["/osmo-relay shows"] = repr(os.listdir(RELAY))
        report["input"] = Path("/osmo/data/input/x.txt").read_text()
        _step(report, "write output", lambda: Path("/osmo/data/output/y.txt").write_text("y"))
        _step(report, "write input (expected: refused)",
              lambda: Path("/osmo/data/input/z.txt").write_text("z"))
        _step(report, "umount the cover (expected: refused)",
              lambda: mounts._checked("umount", mounts._LIBC.umount2(RELAY.encode(), 2)))
        _step(report, "mount again (expected: refused)",
              lambda: mounts.mount_tmpfs("/tmp", 0o755))
        child = os.fork()
        if child == 0:  # a nested user namespace: capabilities again, over locked mounts
            nested: dict[str, str] = {}
            _step(nested, "nested user+mount namespace",
                  lambda: mounts.unshare(0x10000000 | mounts.NEWNS))
            _step(nested, "umount the cover there (expected: refused)",
                  lambda: mounts._checked("umount", mounts._LIBC.umount2(RELAY.encode(), 2)))
            _step(nested, "umount /proc there (expected: refused)",
                  lambda: mounts._checked("umount", mounts._LIBC.umount2(b"/proc", 2)))
            pool.sendall(json.dumps(nested).encode() + b"\n")
            os._exit(0)
        os.waitpid(child, 0)
    pool.sendall(json.dumps(report).encode())
    return 0


def inside(runner: socket.socket) -> None:
    """The runner: fork an attempt for each request of the pool, until it hangs up."""
    for path in ("/osmo/data/input", "/osmo/data/output"):
        os.makedirs(path, exist_ok=True)
    import osmo.runtime.process.mounts  # noqa: F401 - imported once, as a warm runner would
    while True:
        data, fds, _, _ = socket.recv_fds(runner, 64, 2)
        if not data:
            return
        started = time.perf_counter()
        pid = os.fork()
        if pid == 0:
            _attempt(int(data), fds, started)
        for fd in fds:
            os.close(fd)
        os.waitpid(pid, 0)
        runner.sendall(b"done")


# ------------------------------------------------------------------------------ the pool

def podman(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["podman", *args], env=env, capture_output=True, text=True,
                          check=False, timeout=120)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--image", default="localhost/osmo:test")
    ap.add_argument("--attempts", type=int, default=20)
    ap.add_argument("--inside", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.inside:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as runner:
            runner.connect(f"{RELAY}/pool.sock")
            inside(runner)
        return

    from osmo.runtime.process import mounts

    work = Path(tempfile.mkdtemp(prefix="osmo-cwarm-"))
    env = dict(os.environ)
    if "CONTAINERS_CONF" not in env:
        (work / "containers.conf").write_text(CONF)
        env["CONTAINERS_CONF"] = str(work / "containers.conf")
    relay = work / "relay"
    relay.mkdir()
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(relay / "pool.sock"))
    listener.listen(16)
    name = f"osmo-cwarm-probe-{os.getpid()}"
    t0 = time.perf_counter()
    run = podman("run", "-d", "--rm", "--pull=never", "--name", name, "--network", "none",
                 "-v", f"{relay}:{RELAY}", "-v", f"{ROOT}:/opt/osmo-src:ro",
                 "-e", "PYTHONPATH=/opt/osmo-src", args.image,
                 "python3", "/opt/osmo-src/bench/container_warm_probe.py", "--inside", env=env)
    if run.returncode != 0:
        sys.exit(f"podman run: {run.stderr.strip()}")
    try:
        runner, _ = listener.accept()
        print(f"runner container up, connected: {(time.perf_counter() - t0) * 1000:.0f} ms")
        times: list[float] = []
        for i in range(args.attempts):
            folder = work / f"a{i}"
            (folder / "input").mkdir(parents=True)
            (folder / "output").mkdir()
            (folder / "input" / "x.txt").write_text(f"input of attempt {i}")
            clones = [mounts.detached(str(folder / "input"), readonly=True),
                      mounts.detached(str(folder / "output"), readonly=False)]
            t = time.perf_counter()
            socket.send_fds(runner, [str(i).encode()], clones)
            for fd in clones:
                os.close(fd)
            report = serve_attempt(listener)
            runner.recv(4)
            times.append((time.perf_counter() - t) * 1000)
            if i == 0 or "error" in report:
                for key, value in report.items():
                    print(f"  {key}: {value}")
                print(f"  output on the host: {sorted(os.listdir(folder / 'output'))}")
            if "error" in report:
                break
        if times:
            print(f"warm attempt in the container, request → exit seen by the pool: median "
                  f"{statistics.median(times):.1f} ms over {len(times)} (min {min(times):.1f})")
        exec_ms = [timed(podman, "exec", name, "true", env=env) for _ in range(5)]
        print(f"podman exec {name} true: median {statistics.median(exec_ms):.0f} ms")
    finally:
        podman("rm", "-f", "-t", "0", name, env=env)
        listener.close()
    run_ms = [timed(podman, "run", "--rm", "--pull=never", "--network", "none", args.image,
                    "true", env=env) for _ in range(5)]
    print(f"podman run --rm {args.image} true: median {statistics.median(run_ms):.0f} ms")
    shutil.rmtree(work, ignore_errors=True)


def serve_attempt(listener: socket.socket) -> dict[str, str]:
    """Serve one attempt's connection: mount its /proc, collect its report(s)."""
    from osmo.runtime.process import mounts

    conn, _ = listener.accept()
    with conn:
        data, fds, _, _ = socket.recv_fds(conn, 65536, 1)
        if fds:
            mount = mounts.proc_mount(fds[0])
            os.close(fds[0])
            socket.send_fds(conn, [b"proc"], [mount])
            os.close(mount)
            data = b""
        while True:
            more = conn.recv(65536)
            if not more:
                break
            data += more
    report: dict[str, str] = {}
    for line in data.decode().replace("}{", "}\n{").splitlines():
        report.update(json.loads(line))
    return report


def timed(fn: object, *args: str, env: dict[str, str]) -> float:
    t = time.perf_counter()
    fn(*args, env=env)  # type: ignore[operator]
    return (time.perf_counter() - t) * 1000


if __name__ == "__main__":
    main()
