"""Tasks are isolated from each other: environ, attempt folders, inputs (end to end, CLI).

The process sandbox (default wherever bubblewrap works) gives each task its own pid namespace
and ``/proc``, hides osmo's home but for the task's own folders, and binds inputs read-only.
"""

from __future__ import annotations

import os
from pathlib import Path

from tests.conftest import Osmo, ended, write
from tests.e2e.test_datasets import TAMPER_FILE

SECRET = "environ-secret-5b2f7a"

ENVIRON = """
workflow:
  name: environ
  tasks:
  - name: holder
    command: [sh, -c, 'sleep 6']
    credentials:
      api: {API_TOKEN: token}
  - name: thief
    command: [sh, -c, 'for i in $(seq 40); do
        if cat /proc/[0-9]*/environ 2>/dev/null | tr "\\0" "\\n" | grep -q "^API_TOKEN=";
        then echo found > {{output}}/seen; exit 0; fi; sleep 0.1; done;
      echo nothing > {{output}}/seen']
"""

FOLDERS = """
workflow:
  name: folders
  tasks:
  - name: a
    command: [sh, -c, 'echo private > note; echo shared > {{output}}/out']
  - name: b
    command: [sh, -c, 'A=@HOME@/runs/{{workflow_id}}/a/0;
      if cat "$A/work/note" > /dev/null 2>&1; then echo readable; else echo hidden; fi
        > {{output}}/work;
      ls "$A" > {{output}}/listing 2>&1; cat {{input:a}}/out > {{output}}/input; exit 0']
    inputs:
    - task: a
"""

TAMPER = r"""
workflow:
  name: tamper
  tasks:
  - name: make
    command: [sh, -c, 'echo alpha > {{output}}/a.txt; mkdir {{output}}/sub;
      echo beta > {{output}}/sub/b.txt']
  - name: tamper
    command: [sh, /opt/tamper.sh, "{{input:make}}", "{{output}}/ops.txt"]""" + TAMPER_FILE + """\
    inputs:
    - task: make
  - name: read
    command: [sh, -c, 'cat {{input:make}}/a.txt {{input:make}}/sub/b.txt > {{output}}/seen.txt;
      ls {{input:make}} >> {{output}}/seen.txt']
    inputs:
    - task: make
    - task: tamper
"""


def _done(osmo: Osmo, spec: Path) -> dict[str, Path]:
    info = osmo.wait_for(osmo.submit(spec), ended)
    assert info["status"] == "COMPLETED", info
    return {t["name"]: Path(t["output"]) for t in info["tasks"]}


def test_task_cannot_read_another_tasks_environ(osmo: Osmo, tmp_path: Path) -> None:
    osmo("credential", "set", "api", "--payload", f"token={SECRET}", check=True)
    out = _done(osmo, write(tmp_path / "environ.yaml", ENVIRON))
    assert (out["thief"] / "seen").read_text() == "nothing\n"


def test_task_cannot_see_another_attempts_folder(osmo: Osmo, tmp_path: Path) -> None:
    home = str(osmo.home.absolute())
    out = _done(osmo, write(tmp_path / "folders.yaml", FOLDERS.replace("@HOME@", home)))
    assert (out["b"] / "work").read_text() == "hidden\n"
    assert "work" not in (out["b"] / "listing").read_text().split()
    assert (out["b"] / "input").read_text() == "shared\n"  # its own input is there


def test_task_cannot_modify_its_inputs(osmo: Osmo, tmp_path: Path) -> None:
    out = _done(osmo, write(tmp_path / "tamper.yaml", TAMPER))
    ops = (out["tamper"] / "ops.txt").read_text()
    assert "allowed" not in ops and ops.count("denied") == 4, ops
    assert (out["read"] / "seen.txt").read_text() == "alpha\nbeta\na.txt\nsub\n"
    assert (out["make"] / "a.txt").read_text() == "alpha\n"


HOST_TMP = """
workflow:
  name: host-tmp
  tasks:
  - name: writer
    command: [sh, -c, 'echo mine > /tmp/scratch-@ID@; echo leak > /tmp/leak-@ID@;
      sleep 2; cat /tmp/scratch-@ID@ > {{output}}/own']
  - name: reader
    command: [sh, -c, 'sleep 1; for f in @PLANTED@ /tmp/scratch-@ID@; do
        if [ -e "$f" ]; then echo "seen $f"; else echo "absent $f"; fi; done > {{output}}/seen']
"""


def test_task_sees_neither_the_hosts_tmp_nor_another_tasks(osmo: Osmo, tmp_path: Path) -> None:
    """The host's /tmp holds agents' sockets and other users' scratch: a task has its own."""
    planted = Path(f"/tmp/osmo-agent-{tmp_path.name}-{os.getpid()}")
    planted.mkdir()
    ident = f"{tmp_path.name}-{os.getpid()}"
    try:
        spec = HOST_TMP.replace("@ID@", ident).replace("@PLANTED@", str(planted))
        out = _done(osmo, write(tmp_path / "host-tmp.yaml", spec))
        assert (out["writer"] / "own").read_text() == "mine\n"  # its own /tmp works
        assert (out["reader"] / "seen").read_text().split("\n")[:2] == [
            f"absent {planted}", f"absent /tmp/scratch-{ident}"]
        assert not Path(f"/tmp/leak-{ident}").exists(), "a task wrote into the host's /tmp"
    finally:
        planted.rmdir()


UNDO = """
workflow:
  name: undo
  tasks:
  - name: escape
    command: [sh, -c, 'umount @HOME@ 2>/dev/null; umount -l @HOME@ 2>/dev/null;
      if [ -e @HOME@/state.db ]; then echo db-seen; else echo no-db; fi > {{output}}/seen;
      mount -o remount,rw / 2>/dev/null;
      if touch @EVIL@ 2>/dev/null; then echo wrote-host; else echo ro-host; fi >> {{output}}/seen;
      grep "^CapEff" /proc/self/status >> {{output}}/seen']
"""


def test_a_task_cannot_unmount_what_hides_the_control_plane(osmo: Osmo, tmp_path: Path) -> None:
    """A task of a server run as root tries to undo its sandbox: unmount the tmpfs hiding
    osmo's home (the state store, every token) and remount the host writable."""
    evil = Path(f"/usr/osmo-evil-{tmp_path.name}-{os.getpid()}")
    spec = UNDO.replace("@HOME@", str(osmo.home.absolute())).replace("@EVIL@", str(evil))
    try:
        out = _done(osmo, write(tmp_path / "undo.yaml", spec))
        seen = (out["escape"] / "seen").read_text().split()
        assert seen[:2] == ["no-db", "ro-host"], seen
        assert seen[-1] == "0000000000000000", seen  # CapEff: no capability at all
        assert not evil.exists(), "a task wrote to the host's /usr"
    finally:
        evil.unlink(missing_ok=True)
