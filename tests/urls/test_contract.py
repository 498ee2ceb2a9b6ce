"""The Remote contract, run against every scheme (``file://`` and a real ``s3://`` server)."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest

from osmo.errors import UsageError
from osmo.urls import MARKER, UrlError
from osmo.urls.base import PENDING
from tests.urls.conftest import Make

TREE = {
    "a.txt": b"alpha\n",
    "empty.bin": b"",
    "nested/deeper/b.json": b'{"b": 1}\n',
    "nested/with space & $ + ü.txt": "unicode ü\n".encode(),
    "nested/c.mcap": bytes(range(256)) * 513,  # > 128 KiB: several reads
}


def make_tree(root: Path, files: dict[str, bytes]) -> Path:
    for rel, data in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data)
    return root


def read_tree(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes()
            for p in sorted(root.rglob("*")) if p.is_file()}


def leftovers(parent: Path) -> list[str]:
    return [p.name for p in parent.iterdir() if ".osmo-download-" in p.name]


def test_round_trip_nested_with_marker(remote: Make, tmp_path: Path) -> None:
    r = remote("run/out")
    sent = r.upload(make_tree(tmp_path / "src", TREE))
    assert sent == sorted(TREE)
    marker = json.loads(r.store.read(MARKER) or b"")
    assert marker["format"] == "osmo-complete/1"
    assert {f["path"]: (f["size"], f["sha256"]) for f in marker["files"]} == {
        k: (len(v), hashlib.sha256(v).hexdigest()) for k, v in TREE.items()}
    assert r.store.read(PENDING) is None
    got = r.download(tmp_path / "dest")
    assert got == sorted(TREE)
    assert read_tree(tmp_path / "dest") == TREE
    assert leftovers(tmp_path) == []


def test_regex_filters_upload_and_download(remote: Make, tmp_path: Path) -> None:
    r = remote("filtered")
    assert r.upload(make_tree(tmp_path / "src", TREE), regex=r"^nested/") == [
        "nested/c.mcap", "nested/deeper/b.json", "nested/with space & $ + ü.txt"]
    assert r.download(tmp_path / "d1", regex=r"\.(json|mcap)$") == [
        "nested/c.mcap", "nested/deeper/b.json"]
    assert sorted(read_tree(tmp_path / "d1")) == ["nested/c.mcap", "nested/deeper/b.json"]
    with pytest.raises(UsageError, match="invalid regex"):
        r.download(tmp_path / "d2", regex="(")


def test_failed_upload_leaves_no_marker_and_download_refuses(remote: Make,
                                                              tmp_path: Path) -> None:
    r = remote("partial")
    r.upload(make_tree(tmp_path / "v1", {"a.txt": b"v1", "c.txt": b"v1"}))
    v2 = make_tree(tmp_path / "v2", {"a.txt": b"v2 data", "c.txt": b"v2"})
    os.symlink(tmp_path / "gone", v2 / "b.txt")  # sorted between a and c: fails mid-way
    with pytest.raises(UrlError, match="b.txt"):
        r.upload(v2)
    assert r.store.read(MARKER) is None  # the v1 marker was deleted before a.txt changed
    assert r.store.read("a.txt") == b"v2 data"  # so this half-written state is not vouched for
    dest = make_tree(tmp_path / "dest", {"keep.txt": b"mine"})
    with pytest.raises(UrlError, match="still running or failed"):
        r.download(dest)
    assert read_tree(dest) == {"keep.txt": b"mine"}
    os.unlink(v2 / "b.txt")
    assert r.upload(v2) == ["a.txt", "c.txt"]  # a retry completes it
    assert r.download(dest) == ["a.txt", "c.txt"]
    assert read_tree(dest) == {"a.txt": b"v2 data", "c.txt": b"v2", "keep.txt": b"mine"}


def test_corrupt_object_fails_download_and_leaves_dest_untouched(remote: Make,
                                                                  tmp_path: Path) -> None:
    r = remote("corrupt")
    r.upload(make_tree(tmp_path / "src", TREE))
    r.store.write("nested/deeper/b.json", b'{"b": 2}\n')  # same size, different bytes
    with pytest.raises(UrlError, match="does not match"):
        r.download(tmp_path / "dest")
    assert not (tmp_path / "dest").exists()
    assert leftovers(tmp_path) == []


def test_missing_listed_object_fails_download(remote: Make, tmp_path: Path) -> None:
    r = remote("missing")
    r.upload(make_tree(tmp_path / "src", TREE))
    r.store.delete("a.txt")
    with pytest.raises(UrlError, match="a.txt"):
        r.download(tmp_path / "dest")
    assert not (tmp_path / "dest").exists()


def test_data_without_marker_is_downloaded_whole(remote: Make, tmp_path: Path) -> None:
    r = remote("foreign")
    r.store.write("x/1.csv", b"1,2\n")
    r.store.write("y.csv", b"3,4\n")
    assert r.download(tmp_path / "dest") == ["x/1.csv", "y.csv"]
    assert read_tree(tmp_path / "dest") == {"x/1.csv": b"1,2\n", "y.csv": b"3,4\n"}


def test_reupload_replaces_marker_and_stale_objects_are_ignored(remote: Make,
                                                                 tmp_path: Path) -> None:
    r = remote("again")
    r.upload(make_tree(tmp_path / "v1", {"a": b"1", "b": b"1"}))
    r.upload(make_tree(tmp_path / "v2", {"a": b"2"}))
    assert r.download(tmp_path / "dest") == ["a"]
    assert read_tree(tmp_path / "dest") == {"a": b"2"}


def test_empty_folder_round_trips_but_nothing_at_all_is_an_error(remote: Make,
                                                                 tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    assert remote("empty").upload(tmp_path / "empty") == []
    assert remote("empty").download(tmp_path / "d1") == []
    with pytest.raises(UrlError, match="nothing found"):
        remote("never-written").download(tmp_path / "d2")


def test_marker_paths_cannot_escape_dest(remote: Make, tmp_path: Path) -> None:
    r = remote("evil")
    bad = {"format": "osmo-complete/1", "files": [{"path": "../escape", "size": 1,
                                                   "sha256": "00"}]}
    r.store.write(MARKER, json.dumps(bad).encode())
    with pytest.raises(UrlError, match="not a plain relative path"):
        r.download(tmp_path / "dest")
    r.store.write(MARKER, b"{not json")
    with pytest.raises(UrlError, match="not a valid osmo marker"):
        r.download(tmp_path / "dest")
    assert not (tmp_path / "escape").exists()


def test_upload_refuses_bad_sources(remote: Make, tmp_path: Path) -> None:
    r = remote("bad")
    with pytest.raises(UsageError, match="not a folder"):
        r.upload(tmp_path / "nope")
    with pytest.raises(UsageError, match="reserves"):
        r.upload(make_tree(tmp_path / "res", {MARKER: b"{}"}))
    linked = make_tree(tmp_path / "linked", {"a": b"1"})
    os.symlink(tmp_path / "res", linked / "dir")
    with pytest.raises(UsageError, match="symlink to a folder"):
        r.upload(linked)
    assert r.store.read(PENDING) is None  # refused before anything was written
