"""The shared tree walks: iterative, any depth, never through a symlink."""

from __future__ import annotations

import os
from pathlib import Path

from osmo.artifacts.fsops import files, make_dirs, remove_tree


def _nest(root: Path, depth: int) -> None:
    """``depth`` nested folders made by relative names (the whole path may pass PATH_MAX)."""
    fd = os.open(root, os.O_RDONLY | os.O_DIRECTORY)
    try:
        for _ in range(depth):
            os.mkdir("d", dir_fd=fd)
            os.symlink("/", "up", dir_fd=fd)  # must never be followed
            inner = os.open("d", os.O_RDONLY | os.O_DIRECTORY, dir_fd=fd)
            os.close(fd)
            fd = inner
        os.close(os.open("leaf", os.O_WRONLY | os.O_CREAT, 0o644, dir_fd=fd))
    finally:
        os.close(fd)


def test_remove_tree_removes_a_tree_deeper_than_path_max(tmp_path: Path) -> None:
    outside = tmp_path / "keep"
    outside.write_text("mine")
    root = tmp_path / "tree"
    root.mkdir()
    os.symlink(outside, root / "link")
    _nest(root, 2500)  # 5,000 characters of path: more than PATH_MAX
    remove_tree(root)
    assert not root.exists() and outside.read_text() == "mine"


def test_remove_tree_of_a_file_or_nothing(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("x")
    remove_tree(tmp_path / "f")
    remove_tree(tmp_path / "missing")
    assert list(tmp_path.iterdir()) == []


def test_make_dirs_makes_many_levels_and_accepts_existing(tmp_path: Path) -> None:
    deep = tmp_path.joinpath(*["d"] * 1500)  # Path.mkdir(parents=True) recurses here
    try:
        make_dirs(deep)
        make_dirs(deep)
        assert deep.is_dir()
    finally:  # pytest's own cleanup (shutil.rmtree) would recurse too deep
        remove_tree(tmp_path / "d")


def test_files_lists_the_given_depth(tmp_path: Path) -> None:
    (tmp_path / "ab").mkdir()
    (tmp_path / "ab" / "cdef").write_text("x")
    (tmp_path / "top").write_text("x")
    assert list(files(tmp_path, depth=2)) == [tmp_path / "ab" / "cdef"]
    assert list(files(tmp_path, depth=1)) == [tmp_path / "top"]
