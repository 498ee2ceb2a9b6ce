"""Probe (issue 30): what a warm runner inside the sandbox can and cannot do, on this kernel.

Not used by osmo: it tries, as root, the parts a sandboxed warm start would be built from,
and prints one line per step (``ok`` or the errno) and the cost of one attempt's setup.

The runner is a long-lived bubblewrap made as osmo makes a sandbox today
(``osmo.runtime.process.sandbox``: the system folders, osmo's code, the node's network and
user namespace), osmo's home hidden, and ``CAP_SYS_ADMIN`` and ``CAP_SETPCAP`` kept in the
node's user namespace. For each attempt it forks; the child unshares a mount and a pid
namespace and gets its attempt's folders as detached mounts the pool made with
``open_tree(OPEN_TREE_CLONE)`` (read-only ones with ``mount_setattr``) and passed with
``SCM_RIGHTS``, moved into place with ``move_mount``. Its pid 1 needs a ``/proc`` of its own:

- ``mount("proc")`` there is refused (EPERM): bubblewrap's covers in the runner's ``/proc``
  (``/proc/sys``, ``sysrq-trigger``, ...) become locked when the child's mount namespace is
  copied into the node's user namespace, so no ``/proc`` is "fully visible"
  (``mount_too_revealing``); ``fsmount`` by the child is refused alike.
- What works: the child's pid 1 makes the proc context (``fsopen``, ``FSCONFIG_CMD_CREATE``:
  its own pid namespace), the pool (root, in the host's mount namespace) ``fsmount`` s it,
  the child ``move_mount`` s the result on ``/proc`` and binds ``/proc/sys`` read-only.

Then the attacks of a runner that runs a custom type's import code (it is the attempts'
parent, with their uid and their user namespace): while the attempt has never exec'd and
made itself non-dumpable, ``/proc/PID/root``, ``/proc/PID/ns/mnt`` and ``setns`` through a
pidfd are refused; once the attempt execs anything (a typed task that runs a subprocess),
the runner reads the attempt's folders through ``/proc/PID/root`` (the ptrace "read" check
passes: same uid, same user namespace, the attempt's capabilities a subset of the runner's).
That is the blocker for custom types: their import code must not run in a process that is
an ancestor of attempts in their uid.

osmo builds its sandboxed warm starts on these steps for the types it ships only
(``osmo.runtime.process.warm``); this blocker is why a custom type starts cold there.

Usage (as root, from the repository): python bench/warm_sandbox_probe.py [--attempts N]
"""

from __future__ import annotations

import argparse
import ctypes
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

_LIBC = ctypes.CDLL(None, use_errno=True)
_AT_FDCWD = -100
_MOVE_MOUNT_F_EMPTY_PATH = 4
_MOUNT_ATTR_NOSUID, _MOUNT_ATTR_NODEV = 2, 4
_FSCONFIG_CMD_CREATE = 6
_SYS = {"open_tree": 428, "move_mount": 429, "fsopen": 430, "fsconfig": 431, "fsmount": 432,
        "mount_setattr": 442}
_CLONE_NEWNS, _CLONE_NEWPID, _CLONE_NEWUSER = 0x20000, 0x20000000, 0x10000000
_MS_NOSUID, _MS_NODEV, _MS_NOEXEC, _MS_RDONLY = 2, 4, 8, 1
_MS_REMOUNT, _MS_BIND, _MS_REC, _MS_SLAVE = 32, 4096, 16384, 1 << 19
_PR_SET_PDEATHSIG, _PR_SET_DUMPABLE, _PR_CAPBSET_DROP, _PR_SET_NO_NEW_PRIVS = 1, 4, 24, 38


def _call(name: str, result: int) -> int:
    if result < 0:
        errno = ctypes.get_errno()
        raise OSError(errno, f"{name}: {os.strerror(errno)}")
    return result


def _step(name: str, action: object) -> bool:
    """Print ``name: ok`` or ``name: FAILED (errno)``; whether it worked."""
    try:
        result = action() if callable(action) else action
    except OSError as exc:
        print(f"  {name}: FAILED ({exc})", flush=True)
        return False
    print(f"  {name}: ok{'' if result in (None, 0) else f' ({result})'}", flush=True)
    return True


def _mount(source: str | None, target: str, fstype: str | None, flags: int,
           data: str | None = None) -> int:
    enc = [s.encode() if s is not None else None for s in (source, target, fstype, data)]
    return _call(f"mount {target}", _LIBC.mount(enc[0], enc[1], enc[2], flags, enc[3]))


def _move(fd: int, target: str) -> int:
    return _call("move_mount", _LIBC.syscall(_SYS["move_mount"], fd, b"", _AT_FDCWD,
                                             target.encode(), _MOVE_MOUNT_F_EMPTY_PATH))


def _drop_everything() -> None:
    for cap in range(64):
        _LIBC.prctl(_PR_CAPBSET_DROP, cap, 0, 0, 0)
    _call("no_new_privs", _LIBC.prctl(_PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0))

    class Header(ctypes.Structure):
        _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]

    class Data(ctypes.Structure):
        _fields_ = [("effective", ctypes.c_uint32), ("permitted", ctypes.c_uint32),
                    ("inheritable", ctypes.c_uint32)]

    _call("capset", _LIBC.capset(ctypes.byref(Header(0x20080522, 0)), (Data * 2)()))


# ---------------------------------------------------------------- inside the runner's bwrap

def _attempt(sock: socket.socket, home: str, folder: str, fds: list[int], mode: str) -> None:
    """The forked child: namespaces, the attempt's folders, pid 1 with its /proc; never returns."""
    code = 1
    try:
        _LIBC.prctl(_PR_SET_DUMPABLE, 0, 0, 0, 0)  # else the runner reads its /proc/PID/root
        _call("unshare", _LIBC.unshare(_CLONE_NEWNS | _CLONE_NEWPID))
        _mount(None, "/", None, _MS_REC | _MS_SLAVE)
        _mount("tmpfs", home, "tmpfs", _MS_NOSUID | _MS_NODEV, "mode=0755")
        os.makedirs(folder)
        _move(fds[0], folder)  # read-only, then its writable child
        _move(fds[1], os.path.join(folder, "work"))
        _mount("tmpfs", "/tmp", "tmpfs", _MS_NOSUID | _MS_NODEV, "mode=1777")
        init = os.fork()
        if init == 0:
            os._exit(_init(sock, home, folder, mode))
        code = os.waitstatus_to_exitcode(os.waitpid(init, 0)[1])
    except BaseException as exc:  # noqa: BLE001 - a probe: report and exit
        sock.send(json.dumps({"error": str(exc)}).encode())
    os._exit(code)


def _init(sock: socket.socket, home: str, folder: str, mode: str) -> int:
    """pid 1: /proc through the pool, then every capability dropped; reports what it sees."""
    report: dict[str, object] = {}
    try:
        _mount("proc", "/proc", "proc", _MS_NOSUID | _MS_NODEV | _MS_NOEXEC)
        report["mount proc in the child"] = "ok"
    except OSError as exc:
        report["mount proc in the child"] = str(exc)
    context = _call("fsopen", _LIBC.syscall(_SYS["fsopen"], b"proc", 1))
    _call("fsconfig", _LIBC.syscall(_SYS["fsconfig"], context, _FSCONFIG_CMD_CREATE, None,
                                    None, 0))
    own = _LIBC.syscall(_SYS["fsmount"], context, 1, _MOUNT_ATTR_NOSUID | _MOUNT_ATTR_NODEV)
    report["fsmount proc in the child"] = "ok" if own >= 0 else os.strerror(ctypes.get_errno())
    socket.send_fds(sock, [b"fsmount"], [context])
    _, got, _, _ = socket.recv_fds(sock, 64, 1)
    _move(got[0], "/proc")
    _mount("/proc/sys", "/proc/sys", None, _MS_BIND | _MS_REC)
    _mount(None, "/proc/sys", None, _MS_BIND | _MS_REMOUNT | _MS_RDONLY | _MS_NOSUID | _MS_NODEV)
    _LIBC.prctl(_PR_SET_DUMPABLE, 0, 0, 0, 0)
    _drop_everything()
    report.update({
        "pids in its /proc": sorted(int(p) for p in os.listdir("/proc") if p.isdigit()),
        "home shows": sorted(os.listdir(home)),
        "own secret": Path(folder, "secret").read_text(),
        "work writable": os.access(os.path.join(folder, "work"), os.W_OK),
        "folder read-only": not os.access(folder, os.W_OK),
        "CapEff": Path("/proc/self/status").read_text().split("CapEff:")[1].split()[0],
    })
    sock.send(json.dumps(report).encode())
    if mode == "exec":  # what a typed task that runs a subprocess does (its credentials set)
        os.execve("/bin/sleep", ["sleep", "3"], {"PROBE_TOKEN": "S3CRET"})
    if mode == "stay":
        time.sleep(3)
    return 0


def _attack(pid: int, folder: str) -> dict[str, str]:
    """What the runner (a type's import code) reaches of its live attempt ``pid``."""
    out: dict[str, str] = {}
    try:
        stolen = Path(f"/proc/{pid}/root{folder}/secret").read_text()
        out["read /proc/PID/root"] = f"REACHED ({stolen!r})"
    except OSError as exc:
        out["read /proc/PID/root"] = f"refused ({exc.strerror})"
    try:
        os.close(os.open(f"/proc/{pid}/ns/mnt", os.O_RDONLY))
        out["open /proc/PID/ns/mnt"] = "REACHED"
    except OSError as exc:
        out["open /proc/PID/ns/mnt"] = f"refused ({exc.strerror})"
    try:
        environ = Path(f"/proc/{pid}/environ").read_bytes()
        out["read /proc/PID/environ"] = f"REACHED ({b'PROBE_TOKEN' in environ and 'its token'})"
    except OSError as exc:
        out["read /proc/PID/environ"] = f"refused ({exc.strerror})"
    read, write = os.pipe()
    if os.fork() == 0:  # the same, from a process of the runner with no capability at all
        _drop_everything()
        try:
            Path(f"/proc/{pid}/root{folder}/secret").read_text()
            os.write(write, b"REACHED")
        except OSError as exc:
            os.write(write, f"refused ({exc.strerror})".encode())
        os._exit(0)
    os.close(write)
    out["read /proc/PID/root with no capability"] = os.read(read, 200).decode()
    os.close(read)
    os.wait()
    pidfd = os.pidfd_open(pid)
    result = _LIBC.setns(pidfd, _CLONE_NEWNS)  # the runner is single-threaded
    why = os.strerror(ctypes.get_errno())
    out["setns(pidfd, mnt)"] = "REACHED" if result == 0 else f"refused ({why})"
    os.close(pidfd)
    return out


def _runner(fd: int, home: str) -> None:
    sock = socket.socket(fileno=fd)
    status = Path("/proc/self/status").read_text()
    sock.send(json.dumps({"ready": True, "CapEff": status.split("CapEff:")[1].split()[0],
                          "home shows": sorted(os.listdir(home))}).encode())
    while True:
        data, fds, _, _ = socket.recv_fds(sock, 4096, 4)
        if not data:
            return
        request = json.loads(data)
        child = os.fork()
        if child == 0:
            _attempt(sock, home, request["folder"], fds, request["mode"])
        for descriptor in fds:
            os.close(descriptor)
        if request["mode"] in ("stay", "exec"):
            time.sleep(1.5)  # the attempt is set up, dropped its capabilities (and exec'd)
            children = Path(f"/proc/{child}/task/{child}/children").read_text()
            inner = [int(p) for p in children.split()]
            sock.send(json.dumps({"attempt's pid 1": _attack(inner[0], request["folder"]),
                                  "its parent": _attack(child, request["folder"])}).encode())
        os.waitpid(child, 0)


# ---------------------------------------------------------------- the pool (root, the host)

def _detached(path: str, readonly: bool) -> int:
    from osmo.runtime.process import mounts  # the pool's side only: osmo's own adapter

    return mounts.detached(path, readonly=readonly)


def _runner_argv(sandbox: object, view: object, fd: int, home: str) -> list[str]:
    """osmo's sandbox argv around this probe, keeping CAP_SYS_ADMIN and CAP_SETPCAP."""
    source = Path(__file__).read_text()  # by value: its folder need not be visible inside
    argv = sandbox.argv([sys.executable, "-c", source, "--runner", str(fd), home], view)  # type: ignore[attr-defined]
    out: list[str] = []
    for index, arg in enumerate(argv):
        if arg == "--bounding-set=-all":
            arg = "--bounding-set=-all,+sys_admin,+setpcap"
        out.append(arg)
        if index > 0 and argv[index - 1] == "--cap-drop":
            out += ["--cap-add", "CAP_SYS_ADMIN"]
    return out


def _serve(sock: socket.socket, folder: str, mode: str) -> tuple[dict[str, object], float]:
    """One attempt: its detached folders, the fork, the /proc relay; its report and seconds."""
    began = time.perf_counter()
    fds = [_detached(folder, True), _detached(os.path.join(folder, "work"), False)]
    socket.send_fds(sock, [json.dumps({"folder": folder, "mode": mode}).encode()], fds)
    for fd in fds:
        os.close(fd)
    data, got, _, _ = socket.recv_fds(sock, 65536, 1)
    if got:  # the attempt's pid 1 asks for its /proc
        mounted = _call("fsmount", _LIBC.syscall(_SYS["fsmount"], got[0], 1,
                                                 _MOUNT_ATTR_NOSUID | _MOUNT_ATTR_NODEV))
        socket.send_fds(sock, [b"proc"], [mounted])
        os.close(mounted)
        os.close(got[0])
        data = sock.recv(65536)
    return json.loads(data), time.perf_counter() - began


def main() -> None:
    """Run the probe (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runner", nargs=2, metavar=("FD", "HOME"))
    parser.add_argument("--attempts", type=int, default=20)
    args = parser.parse_args()
    if args.runner:
        _LIBC.prctl(_PR_SET_PDEATHSIG, 9, 0, 0, 0)
        _runner(int(args.runner[0]), args.runner[1])
        return
    from osmo.runtime.process import sandbox as sandboxes

    if os.geteuid() != 0:
        sys.exit("run it as root: a non-root osmo's tasks share its uid (see the report)")
    found = sandboxes.choose("on")
    assert found is not None
    network = sandboxes.node_network(outbound=False)
    home = tempfile.mkdtemp(prefix="osmo-probe-", dir="/var/tmp")
    try:
        os.chmod(home, 0o700)
        folders = []
        for name in ("a1", "a2"):
            folder = os.path.join(home, name)
            os.makedirs(os.path.join(folder, "work"))
            Path(folder, "secret").write_text(name)
            os.chown(os.path.join(folder, "work"), 65534, 65534)
            os.chmod(folder, 0o755)
            folders.append(folder)
        sandbox = found.joined(network)
        view = sandboxes.View(hidden=(Path(home),), readonly=(), writable=(), cwd=Path("/"))
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        with sandbox.entered():
            runner = subprocess.Popen(_runner_argv(sandbox, view, theirs.fileno(), home),
                                      pass_fds=(theirs.fileno(), *sandbox.fds))
        theirs.close()
        print("runner:", ours.recv(65536).decode(), flush=True)
        report, _ = _serve(ours, folders[0], "report")
        print("attempt a1:", json.dumps(report), flush=True)
        for mode in ("stay", "exec"):
            report, _ = _serve(ours, folders[1], mode)
            print(f"runner attacks a2 ({mode}):", ours.recv(65536).decode(), flush=True)
        times = [_serve(ours, folders[i % 2], "report")[1] for i in range(args.attempts)]
        print(f"setup of one attempt (fork, namespaces, folders, /proc relay, caps dropped): "
              f"median {statistics.median(times) * 1000:.2f} ms of {len(times)}", flush=True)
        ours.close()
        runner.wait(timeout=30)
    finally:
        network.close()
        shutil.rmtree(home, ignore_errors=True)


if __name__ == "__main__":
    main()
