"""Hostile outputs: whatever a task leaves in its output folder, its attempt finishes (COMPLETED
or FAILED with a reason and a documented code), its cpu slot is released and its mounted
credential files are deleted (issue 11, item 2; items 6 and the output limit add kinds).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.artifacts.fsops import remove_tree
from osmo.status import ExitCode
from tests.conftest import Osmo, write
from tests.hostile.datarun import finished, tasks

# Folders made one level at a time with relative names: the path may exceed PATH_MAX.
NEST = """
import os, sys
os.chdir(os.environ["OSMO_OUTPUT"])
for _ in range(int(sys.argv[1])):
    os.mkdir("d")
    os.chdir("d")
open("leaf.txt", "w").write("deep\\n")
"""


@pytest.fixture
def deep(osmo: Osmo, tmp_path: Path) -> Iterator[None]:
    """Removes the deep trees after the server stopped (pytest's cleanup would recurse)."""
    yield
    osmo.stop_server()
    for child in tmp_path.iterdir():
        remove_tree(child, ignore_errors=True)


def _task(name: str, command: str, extra: str = "") -> str:
    return f"""
  - name: {name}
    command: [sh, -c, {json.dumps(command)}]
    credentials: {{vault: /etc/vault}}
    files:
    - path: /tmp/nest.py
      contents: {json.dumps(NEST)}{extra}
"""


def _kinds(tmp_path: Path) -> Path:
    return write(tmp_path / "kinds.yaml", """
workflow:
  name: kinds
  resources:
    default: {cpu: 1}
  tasks:""" + _task("deep", "python3 /tmp/nest.py 600")
        + _task("deeper", "python3 /tmp/nest.py 2100")
        + _task("escape", "ln -s /etc/passwd {{output}}/passwd"))


def _cpu_used(osmo: Osmo) -> float:
    nodes = json.loads(osmo("resource", "list", "--format", "json", check=True).out)
    return float(sum(n["used"]["cpu"] for n in nodes))


def test_every_output_failure_kind_finishes_and_releases_slot_and_secrets(
        osmo: Osmo, tmp_path: Path, deep: None) -> None:
    osmo("credential", "set", "vault", "--payload", "key=s3cr3t-value", check=True)
    wf = finished(osmo, _kinds(tmp_path), code=1)  # some of them failed, and --wait returned
    by_name = tasks(osmo, wf)

    assert by_name["deep"]["status"] == "COMPLETED", by_name["deep"]  # 600 levels: walked fine
    got = tmp_path / "got"
    osmo("artifacts", "get", f"{wf}:deep", "-o", str(got), check=True)
    assert (got / ("d/" * 600) / "leaf.txt").read_text() == "deep\n"

    for name, words in (("deeper", "too deep"), ("escape", "outside the output folder")):
        task = by_name[name]
        assert task["status"] == "FAILED" and task["exit_code"] == ExitCode.OUTPUT_ERROR, task
        assert words in task["message"], task
    assert _cpu_used(osmo) == 0
    for name in by_name:  # every attempt had its credential mounted, and it is gone now
        vault = osmo.home / "runs" / wf / name / "0" / "files" / "etc" / "vault"
        assert vault.is_dir() and list(vault.iterdir()) == [], f"{name} left its secret behind"


def test_a_hard_link_to_an_outside_file_is_copied_never_changed(osmo: Osmo,
                                                                tmp_path: Path) -> None:
    outside = tmp_path / "outside.txt"
    outside.write_text("before\n")
    outside.chmod(0o644)
    # unsandboxed: in the sandbox OSMO_HOME is hidden and a link across its mounts fails
    osmo("server", "start", "--sandbox", "off", check=True)
    db = osmo.home / "state.db"
    db_mode = db.stat().st_mode
    spec = write(tmp_path / "link.yaml", f"""
workflow:
  name: links
  tasks:
  - name: t
    command: [sh, -c, "ln {outside} {{{{output}}}}/outside.txt && ln {db} {{{{output}}}}/db"]
""")
    wf = finished(osmo, spec)
    assert db.stat().st_mode == db_mode  # never chmod-ed
    assert outside.stat().st_mode & 0o777 == 0o644
    blobs = osmo.home / "artifacts" / "blobs"
    assert outside.stat().st_ino not in {p.stat().st_ino for p in blobs.rglob("*")}
    outside.write_text("changed later\n")  # the outside file is still its owner's to change
    got = tmp_path / "got"
    osmo("artifacts", "get", f"{wf}:t", "-o", str(got), check=True)
    assert (got / "outside.txt").read_text() == "before\n"  # the artifact did not change
    assert _cpu_used(osmo) == 0


def test_an_output_over_the_tasks_storage_limit_fails_clearly(osmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "big.yaml", """
workflow:
  name: sizes
  resources:
    default: {cpu: 1, storage: 4Ki}
  tasks:
  - name: small
    command: [sh, -c, "head -c 3000 /dev/zero > {{output}}/a"]
  - name: big
    command: [sh, -c, "head -c 3000 /dev/zero > {{output}}/a; head -c 3000 /dev/urandom > {{output}}/b"]
""")
    wf = finished(osmo, spec, code=1)
    by_name = tasks(osmo, wf)
    assert by_name["small"]["status"] == "COMPLETED"
    big = by_name["big"]
    assert big["status"] == "FAILED" and big["exit_code"] == ExitCode.OUTPUT_ERROR, big
    assert "6000 bytes in 2 files" in big["message"] and "storage" in big["message"], big
    assert _cpu_used(osmo) == 0
    blobs = osmo.home / "artifacts" / "blobs"
    assert len([p for p in blobs.rglob("*") if p.is_file()]) == 1  # nothing of big was stored
