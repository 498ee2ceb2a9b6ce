"""Spec files and ``localpath`` files that are not regular files: refused by what they are.

A FIFO with no writer used to hang ``osmo validate`` forever; ``/dev/zero`` was called a
folder. Each is now an exit-2 error naming the kind of file, and nothing blocks.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from osmo.errors import SpecError
from osmo.spec import load_spec
from tests.conftest import REPO, Osmo, write

HEAD = "workflow:\n  name: files\n  tasks:\n  - name: a\n    command: [echo]\n"


def _osmo(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "osmo", *args], capture_output=True,
                          text=True, timeout=60, cwd=REPO, env=env)


@pytest.fixture
def fifo(tmp_path: Path) -> Path:
    path = tmp_path / "wf.yaml"
    os.mkfifo(path)
    return path


@pytest.mark.parametrize("args", [["validate"], ["submit", "--dry-run"]])
def test_a_fifo_spec_is_refused_without_hanging(fifo: Path, args: list[str]) -> None:
    r = _osmo(*args, str(fifo))
    assert r.returncode == 2, r
    assert f"{fifo}: is a FIFO (named pipe), not a regular file" in r.stderr


def test_submit_of_a_fifo_to_a_local_server(osmo: Osmo, fifo: Path) -> None:
    r = osmo("submit", str(fifo), timeout=60)
    assert r.code == 2 and "is a FIFO (named pipe), not a regular file" in r.err, r


@pytest.mark.parametrize("target,kind", [("/dev/zero", "a character device"),
                                         ("/dev/null", "a character device"),
                                         (".", "a folder")])
def test_special_spec_files_are_named(target: str, kind: str) -> None:
    with pytest.raises(SpecError, match=f"is {kind}, not a regular file"):
        load_spec(target)


def test_a_huge_spec_file_is_refused(tmp_path: Path) -> None:
    big = tmp_path / "big.yaml"
    with big.open("wb") as f:
        f.truncate(17 * 2**20)  # sparse: no disk used
    with pytest.raises(SpecError, match="is larger than 16 MiB, the limit"):
        load_spec(big)


@pytest.mark.parametrize("target,kind", [("/dev/zero", "a character device"),
                                         ("FIFO", "a FIFO (named pipe)")])
def test_localpath_that_is_not_a_regular_file(tmp_path: Path, target: str, kind: str) -> None:
    if target == "FIFO":
        os.mkfifo(tmp_path / "pipe")
        target = "pipe"
    spec = write(tmp_path / "wf.yaml", HEAD + f"    files:\n    - path: /x\n"
                 f"      localpath: {target}\n")
    r = _osmo("validate", str(spec), "--allow-localpath", "/dev")
    assert r.returncode == 2, r
    assert (f"{spec}:8:18: localpath '{target}' in task 'a' is {kind}, not a regular file"
            in r.stderr), r.stderr
