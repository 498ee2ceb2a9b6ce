"""``osmo artifacts get -o DEST`` with a hostile or careless DEST: never a write through a
symlink, never a traceback (issue 11, medium items)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.conftest import Osmo, write
from tests.hostile.datarun import finished

SPEC = """
workflow:
  name: files
  tasks:
  - name: t
    command: [sh, -c, "mkdir {{output}}/sub && echo inner > {{output}}/sub/x.txt && echo top > {{output}}/top.txt"]
"""


@pytest.fixture(scope="module")
def made(shared_osmo: Osmo, tmp_path_factory: pytest.TempPathFactory) -> str:
    spec = write(tmp_path_factory.mktemp("spec") / "s.yaml", SPEC)
    return finished(shared_osmo, spec)


def _get(osmo: Osmo, wf: str, dest: Path, *args: str):  # type: ignore[no-untyped-def]
    return osmo("artifacts", "get", f"{wf}:t", "-o", str(dest), *args)


def test_a_symlinked_folder_inside_dest_is_never_written_through(
        shared_osmo: Osmo, made: str, tmp_path: Path) -> None:
    outside = tmp_path / "outside"
    outside.mkdir()
    dest = tmp_path / "dest"
    dest.mkdir()
    os.symlink(outside, dest / "sub")
    r = _get(shared_osmo, made, dest)
    assert r.code == 2, r.out + r.err
    assert "symlink" in r.err and "Traceback" not in r.err
    assert list(outside.iterdir()) == []
    assert not (dest / "top.txt").exists()  # refused before anything was written


def test_a_symlinked_file_inside_dest_is_replaced_not_followed(
        shared_osmo: Osmo, made: str, tmp_path: Path) -> None:
    victim = tmp_path / "victim.txt"
    victim.write_text("mine\n")
    dest = tmp_path / "dest"
    dest.mkdir()
    os.symlink(victim, dest / "top.txt")
    r = _get(shared_osmo, made, dest)
    assert r.code == 0, r.out + r.err
    assert victim.read_text() == "mine\n"
    assert not (dest / "top.txt").is_symlink() and (dest / "top.txt").read_text() == "top\n"


@pytest.mark.parametrize("kind", ["file", "dangling symlink"])
def test_dest_that_is_not_a_folder_is_refused_or_forced(
        shared_osmo: Osmo, made: str, tmp_path: Path, kind: str) -> None:
    dest = tmp_path / "dest"
    target = tmp_path / "nowhere"
    if kind == "file":
        dest.write_text("keep me\n")
    else:
        os.symlink(target, dest)
    r = _get(shared_osmo, made, dest)
    assert r.code == 2, r.out + r.err
    assert "not a folder" in r.err and "--force" in r.err and "Traceback" not in r.err
    assert dest.is_symlink() if kind != "file" else dest.read_text() == "keep me\n"
    r = _get(shared_osmo, made, dest, "--force")
    assert r.code == 0, r.out + r.err
    assert (dest / "sub" / "x.txt").read_text() == "inner\n" and not dest.is_symlink()
    assert not target.exists()  # the dangling link was replaced, not followed
