"""What a sandboxed task sees of the host: only what it needs (end to end, CLI).

The attacks: a task of a server running as root reads the token file the server was given
(``--accept-token``, where the Helm chart mounts it), the shadow files, the host's homes,
``/var``, ``/run`` and another worker's home; writes the host's kernel settings through
``/proc/sys``; shares the host's IPC, UTS, network and user namespaces; runs as root on the
host, so that a process of the same uid reads its secret environment.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.layout import Home
from tests.conftest import Osmo, ended, unique_sleep, wait_no_process, write
from tests.e2e.cluster import Cluster

ROOT = os.geteuid() == 0


def _done(osmo: Osmo, spec: Path) -> dict[str, Path]:
    info = osmo.wait_for(osmo.submit(spec), ended)
    assert info["status"] == "COMPLETED", (info, osmo("logs", info["id"]).out)
    return {t["name"]: Path(t["output"]) for t in info["tasks"]}


SEEN = """
workflow:
  name: seen
  tasks:
  - name: look
    command: [sh, -c, 'for f in "$@"; do if cat "$f" > /dev/null 2>&1; then echo "read $f";
      elif [ -e "$f" ]; then echo "denied $f"; else echo "absent $f"; fi; done
      > {{output}}/seen', sh, @FILES@]
"""


def seen_spec(tmp_path: Path, files: list[str]) -> Path:
    return write(tmp_path / "seen.yaml", SEEN.replace("@FILES@", ", ".join(
        json.dumps(f) for f in files)))


def read_lines(out: Path) -> list[str]:
    return [line for line in (out / "seen").read_text().splitlines() if line.startswith("read")]


@pytest.fixture
def planted() -> Iterator[list[Path]]:
    """Marker files in the host folders a task must not see (removed afterwards)."""
    tag = f"osmo-test-{uuid.uuid4().hex[:12]}"
    made: list[Path] = []
    folders = [Path("/root"), Path("/home"), Path("/var/tmp"), Path("/srv"), Path("/run"),
               Path("/mnt"), Path("/media")]
    try:
        for folder in folders:
            if folder.is_dir():
                marker = folder / tag
                marker.write_text("host-only\n")
                marker.chmod(0o644)
                made.append(marker)
        yield made
    finally:
        for marker in made:
            marker.unlink(missing_ok=True)


@pytest.fixture
def tokens() -> Iterator[list[Path]]:
    """Token files as the Helm chart mounts them (/etc/osmo/tokens/NAME), one elsewhere, and
    an ssh host key (all readable by anyone who can see them)."""
    tag = f"osmo-test-{uuid.uuid4().hex[:12]}"
    chart = Path("/etc/osmo/tokens")
    created = [p for p in (Path("/etc/osmo"), chart) if not p.exists()]
    chart.mkdir(parents=True, exist_ok=True)
    other = Path(f"/opt/{tag}")
    other.mkdir()
    Path("/etc/ssh").mkdir(exist_ok=True)
    files = [chart / tag, other / "token", Path(f"/etc/ssh/ssh_host_{tag}_key")]
    for i, path in enumerate(files):
        path.write_text(f"token-{i}-{tag}\n")
        path.chmod(0o644)  # readable by anyone who can see it: the sandbox must hide it
    try:
        yield files
    finally:
        for path in files:
            path.unlink(missing_ok=True)
        other.rmdir()
        for folder in reversed(created):
            try:
                folder.rmdir()
            except OSError:
                pass  # another test's files are in it now


def test_a_task_sees_no_token_file_nor_the_hosts_private_folders(
        osmo: Osmo, tmp_path: Path, planted: list[Path], tokens: list[Path]) -> None:
    args = [a for i, t in enumerate(tokens[:2])
            for a in ("--accept-token", f"probe{i}:admin:{t}")]
    osmo("server", "start", *args, check=True)
    files = [str(p) for p in (*planted, *tokens)] + ["/etc/shadow", "/etc/gshadow"]
    out = _done(osmo, seen_spec(tmp_path, files))["look"]
    assert read_lines(out) == [], (out / "seen").read_text()


def test_a_task_still_sees_the_system_folders(osmo: Osmo, tmp_path: Path) -> None:
    out = _done(osmo, seen_spec(tmp_path, ["/etc/passwd", "/usr/bin/env", "/bin/sh",
                                           "/etc/hostname"]))["look"]
    assert len(read_lines(out)) == 4, (out / "seen").read_text()


def test_a_task_sees_no_other_workers_home(tmp_path: Path) -> None:
    """Two workers of one host, their homes outside /tmp (as /var/lib/osmo-NAME would be):
    a task of one reads nothing of the other's (its worker file, its token)."""
    root = Path(f"/var/tmp/osmo-test-{uuid.uuid4().hex[:12]}")
    root.mkdir()
    cluster = Cluster(root)
    try:
        cluster.start_server()
        cluster.start_worker("w2", pool="other")
        cluster.start_worker("w1", env={"OSMO_SANDBOX_SHARE": str(tmp_path)})
        secret = root / "w2" / "worker-token"
        secret.write_text("w2-secret\n")
        files = [str(root / "w2" / "worker" / "worker.json"), str(secret),
                 str(root / "server" / "state.db")]
        wf = cluster.osmo.submit(seen_spec(tmp_path, files))
        assert cluster.osmo.wait_for(wf, ended)["status"] == "COMPLETED"
        got = tmp_path / "got"
        cluster.osmo("artifacts", "get", f"{wf}:look", "-o", str(got), check=True)
        assert read_lines(got) == [], (got / "seen").read_text()
    finally:
        cluster.stop()
        shutil.rmtree(root, ignore_errors=True)


POKE = """
import os, sys
out = open(sys.argv[1] + "/poke", "w")
name = open("/proc/sys/kernel/hostname").read()
for path, data in (("/proc/sys/kernel/hostname", name), ("/proc/sys/kernel/core_pattern", "")):
    try:
        fd = os.open(path, os.O_WRONLY)
        print("opened", path, file=out)
        if data:
            print("wrote", os.write(fd, data.encode()), file=out)
        os.close(fd)
    except OSError as exc:
        print("refused", path, exc.strerror, file=out)
for ns in ("net", "ipc", "uts", "user", "pid", "mnt"):
    print(ns, os.readlink("/proc/self/ns/" + ns), file=out)
"""

KERNEL = f"""
workflow:
  name: kernel
  tasks:
  - name: poke
    command: [python3, /tmp/poke.py, "{{{{output}}}}"]
    files: [{{path: /tmp/poke.py, contents: {json.dumps(POKE)}}}]
"""


def test_a_task_cannot_write_the_kernels_settings_and_has_namespaces_of_its_own(
        osmo: Osmo, tmp_path: Path) -> None:
    """As root, the host's /proc/sys was writable (kernel.hostname, core_pattern: host
    root). Writing the same hostname back is harmless if the attack works."""
    out = _done(osmo, write(tmp_path / "kernel.yaml", KERNEL))["poke"]
    lines = (out / "poke").read_text().splitlines()
    assert not [line for line in lines if line.startswith(("opened", "wrote"))], lines
    theirs = dict(line.split(" ", 1) for line in lines if not line.startswith("refused"))
    for ns in ("net", "ipc", "uts", "user", "pid", "mnt"):
        assert theirs[ns] != os.readlink(f"/proc/self/ns/{ns}"), (ns, lines)


def wait_for_process(marker: str, timeout: float = 60) -> tuple[int, int]:
    """(pid, uid on the host) of the task process that has ``marker`` as an argument."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for name in os.listdir("/proc"):
            try:
                if name.isdigit() and marker.encode() in Path(
                        f"/proc/{name}/cmdline").read_bytes().split(b"\0"):
                    status = Path(f"/proc/{name}/status").read_text()
                    uid = next(ln for ln in status.splitlines() if ln.startswith("Uid:"))
                    return int(name), int(uid.split()[1])
            except (OSError, StopIteration):
                continue
        time.sleep(0.05)
    raise AssertionError(f"no process with {marker}")


@pytest.mark.skipif(not ROOT, reason="the server must run as root")
def test_a_root_servers_task_is_not_root_on_the_host(osmo: Osmo, tmp_path: Path) -> None:
    """Its uid on the host is unprivileged, and a process of that same uid outside the
    sandbox cannot read its secret environment (``ps eww``); its output is still taken in
    (read, ingested) and its attempt folder removed by the server."""
    osmo("credential", "set", "api", "--payload", "token=environ-secret-81c3", check=True)
    marker = unique_sleep()
    spec = write(tmp_path / "uid.yaml", f"""
workflow:
  name: uid
  tasks:
  - name: t
    command: [sh, -c, 'echo made > {{{{output}}}}/data; mkdir {{{{output}}}}/sub;
      echo x > {{{{output}}}}/sub/private; chmod 600 {{{{output}}}}/sub/private;
      sleep {marker} & while [ ! -e go ]; do sleep 0.05; done; kill $!']
    credentials:
      api: {{API_TOKEN: token}}
""")
    wf = osmo.submit(spec)
    pid, uid = wait_for_process(marker)
    assert uid != 0, "a root server's task runs as root on the host"
    snoop = subprocess.run(["setpriv", f"--reuid={uid}", f"--regid={uid}", "--clear-groups",
                            "cat", f"/proc/{pid}/environ"], capture_output=True)
    assert b"environ-secret-81c3" not in snoop.stdout
    (Home(osmo.home).attempt(wf, "t", 0).work / "go").write_text("")  # the task then ends
    wait_no_process(marker)
    info = osmo.wait_for(wf, ended)
    out = Path(info["tasks"][0]["output"])
    assert (out / "data").read_text() == "made\n" and (out / "sub" / "private").exists()
    got = tmp_path / "got"
    osmo("artifacts", "get", f"{wf}:t", "-o", str(got), check=True)
    assert (got / "sub" / "private").read_text() == "x\n"


SHARES = """
workflow:
  name: shares
  tasks:
  - name: t
    command: [sh, -c, 'cat @DATA@/in.txt > {{output}}/read;
      if echo x > @DATA@/new 2>/dev/null; then echo wrote; else echo refused; fi > {{output}}/data;
      echo y > @SCRATCH@/made && echo wrote > {{output}}/scratch']
"""


def test_a_read_only_share_is_read_only_and_a_share_writable(osmo: Osmo, tmp_path: Path) -> None:
    """``DIR:ro`` (here through OSMO_SANDBOX_SHARE, ':'-separated) for datasets and
    environments; a plain ``DIR`` stays writable (by the tasks' uid: the operator makes it
    so, here mode 1777)."""
    data, scratch = tmp_path / "data", tmp_path / "scratch"
    data.mkdir()
    (data / "in.txt").write_text("dataset\n")
    scratch.mkdir(mode=0o1777)
    scratch.chmod(0o1777)
    osmo.env["OSMO_SANDBOX_SHARE"] = f"{data}:ro:{scratch}"
    spec = write(tmp_path / "shares.yaml",
                 SHARES.replace("@DATA@", str(data)).replace("@SCRATCH@", str(scratch)))
    out = _done(osmo, spec)["t"]
    assert (out / "read").read_text() == "dataset\n"
    assert (out / "data").read_text() == "refused\n" and not (data / "new").exists()
    assert (out / "scratch").read_text() == "wrote\n" and (scratch / "made").exists()


def test_a_typed_tasks_own_folder_shows_its_code_but_never_osmos_home(
        osmo: Osmo, tmp_path: Path) -> None:
    """A typed task imports its type from the spec's folder, shown read-only; osmo's home
    lies inside that folder here and stays hidden (no share shows the folder otherwise)."""
    osmo.env["OSMO_SANDBOX_SHARE"] = ""
    db = osmo.home / "state.db"
    write(tmp_path / "peek.py", f"""
from osmo import task_type

@task_type(version="1")
def peek(ctx):
    try:
        open({str(db)!r}, "rb").read(1)
        seen = "read"
    except OSError:
        seen = "hidden"
    (ctx.output / "seen").write_text(seen)
""")
    out = _done(osmo, write(tmp_path / "peek.yaml", """
workflow:
  name: peek
  tasks:
  - name: t
    type: peek:peek
"""))["t"]
    assert db.exists() and (out / "seen").read_text() == "hidden"
