"""Private, checked copies: what a task is handed is never a blob, and a blob that no longer
matches its digest is never handed out nor re-used (issue 11, item 5)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from osmo.artifacts import ArtifactCorrupted, ArtifactStore
from tests.artifacts.test_store import _corrupt, _digest, _write


@pytest.fixture
def store(tmp_path: Path) -> ArtifactStore:
    return ArtifactStore(tmp_path / "home" / "artifacts")


def test_copies_are_private_and_writable(store: ArtifactStore, tmp_path: Path) -> None:
    m = store.ingest(_write(tmp_path / "out", {"a/data.txt": b"original\n"}))
    mine = tmp_path / "mine"
    store.copy_tree(m, mine)
    assert os.stat(mine / "a/data.txt").st_ino != os.stat(store.path(m.entries[0].digest)).st_ino
    with open(mine / "a/data.txt", "ab") as f:  # a task appending to its input
        f.write(b"x\n")
    assert store.read(_digest(b"original\n")) == b"original\n"
    theirs = tmp_path / "theirs"
    store.copy_tree(m, theirs)
    assert (theirs / "a/data.txt").read_bytes() == b"original\n"


@pytest.mark.parametrize("first_known_intact", [False, True])
def test_a_changed_blob_is_never_handed_out(store: ArtifactStore, tmp_path: Path,
                                           first_known_intact: bool) -> None:
    m = store.ingest(_write(tmp_path / "out", {"data.txt": b"original\n"}))
    if first_known_intact:  # a copy made before: the blob is remembered as intact (once it
        time.sleep(1.1)     # has not changed for a second: file times tick coarsely)
        store.copy_tree(m, tmp_path / "before")
    _corrupt(store, _digest(b"original\n"))
    with pytest.raises(ArtifactCorrupted, match="now hashes to"):
        store.copy_tree(m, tmp_path / "after")
    with pytest.raises(ArtifactCorrupted):
        store.materialize(m, tmp_path / "got")
    assert not (tmp_path / "got" / "data.txt").exists()


def test_a_changed_blob_is_replaced_not_reused_by_the_next_ingest(store: ArtifactStore,
                                                                  tmp_path: Path) -> None:
    m = store.ingest(_write(tmp_path / "one", {"data.txt": b"original\n"}))
    _corrupt(store, _digest(b"original\n"))
    again = store.ingest(_write(tmp_path / "two", {"data.txt": b"original\n"}))
    assert again == m
    assert store.read(_digest(b"original\n")) == b"original\n"  # healed by the new output
    store.copy_tree(m, tmp_path / "copy")
    assert (tmp_path / "copy" / "data.txt").read_bytes() == b"original\n"


def test_materialize_never_writes_through_a_symlink(store: ArtifactStore, tmp_path: Path) -> None:
    from osmo.errors import UsageError

    m = store.ingest(_write(tmp_path / "out", {"sub/x": b"x", "top": b"t"}))
    outside = tmp_path / "outside"
    outside.mkdir()
    dest = tmp_path / "dest"
    dest.mkdir()
    (dest / "sub").symlink_to(outside)
    with pytest.raises(UsageError, match="symlink"):
        store.materialize(m, dest)
    assert list(outside.iterdir()) == [] and not (dest / "top").exists()
    (tmp_path / "file").write_text("keep")
    with pytest.raises(UsageError, match="not a folder"):
        store.materialize(m, tmp_path / "file")
    assert (tmp_path / "file").read_text() == "keep"
