"""The blob store on real files: ingest, dedup, verified reads, materialize, gc, concurrency."""

from __future__ import annotations

import hashlib
import os
import shutil
import stat
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.artifacts import ArtifactCorrupted, ArtifactStore, Entry, Manifest, OutputRejected
from osmo.errors import NotFoundError, UsageError


def _digest(data: bytes) -> str:
    return "sha256:" + hashlib.sha256(data).hexdigest()


def _write(root: Path, files: dict[str, bytes]) -> Path:
    for rel, data in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    return root


def _corrupt(store: ArtifactStore, digest: str) -> None:
    """Flip the first byte of a blob (it is read-only: make it writable first)."""
    blob = store.path(digest)
    os.chmod(blob, 0o644)
    data = bytearray(blob.read_bytes())
    data[0] ^= 0xFF
    with open(blob, "r+b") as f:  # in place: the inode (and the output sharing it) changes
        f.write(data)


@pytest.fixture
def store(tmp_path: Path) -> ArtifactStore:
    return ArtifactStore(tmp_path / "home" / "artifacts")


FILES = {
    "top.txt": b"hello\n",
    "empty": b"",
    "a/b/c/deep.bin": os.urandom(3 * (1 << 20) + 17),  # several 1 MiB reads, odd tail
    "a/sibling.txt": b"hello\n",  # same content as top.txt
    "sp ace/ü.txt": b"unicode",
}


def test_ingest_lists_every_file_with_its_digest(store: ArtifactStore, tmp_path: Path) -> None:
    out = _write(tmp_path / "out", FILES)
    m = store.ingest(out)
    assert m.entries == tuple(sorted((Entry(p, _digest(d), len(d)) for p, d in FILES.items()),
                                     key=lambda e: e.path))
    assert m.size == sum(map(len, FILES.values()))
    for data in FILES.values():
        assert store.has(_digest(data)) and store.read(_digest(data)) == data
        assert store.verify(_digest(data))
    blobs = [p for p in (store.root / "blobs" / "sha256").rglob("*") if p.is_file()]
    assert len(blobs) == 4  # top.txt and a/sibling.txt share one blob
    h = _digest(FILES["top.txt"])[7:]
    assert store.path(_digest(FILES["top.txt"])) == store.root / "blobs/sha256" / h[:2] / h[2:]


def test_same_filesystem_ingest_links_and_makes_outputs_read_only(
        store: ArtifactStore, tmp_path: Path) -> None:
    out = _write(tmp_path / "out", {"f": b"data"})
    store.ingest(out)
    blob = store.path(_digest(b"data"))
    assert os.stat(blob).st_ino == os.stat(out / "f").st_ino  # a link: nothing was copied
    assert stat.S_IMODE(os.stat(out / "f").st_mode) == 0o444
    assert not list((store.root / "tmp").iterdir())


def test_a_file_with_several_links_is_copied_and_left_alone(store: ArtifactStore,
                                                            tmp_path: Path) -> None:
    outside = tmp_path / "outside"
    outside.write_bytes(b"someone else's")
    outside.chmod(0o600)
    out = tmp_path / "out"
    out.mkdir()
    os.link(outside, out / "f")
    store.ingest(out)
    blob = store.path(_digest(b"someone else's"))
    assert os.stat(blob).st_ino != os.stat(outside).st_ino  # a copy
    assert stat.S_IMODE(os.stat(outside).st_mode) == 0o600  # never chmod-ed
    outside.write_bytes(b"changed")
    assert store.read(_digest(b"someone else's")) == b"someone else's"


def test_empty_folder_gives_empty_manifest(store: ArtifactStore, tmp_path: Path) -> None:
    (tmp_path / "out" / "only" / "dirs").mkdir(parents=True)
    assert store.ingest(tmp_path / "out") == Manifest(())


def test_ingest_refuses_a_missing_folder(store: ArtifactStore, tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="not a folder"):
        store.ingest(tmp_path / "nope")


def test_second_ingest_of_same_content_writes_nothing(store: ArtifactStore,
                                                      tmp_path: Path) -> None:
    data = os.urandom(1 << 20)
    first = store.ingest(_write(tmp_path / "one", {"x.bin": data}))
    blob = store.path(_digest(data))
    before = os.stat(blob)
    time.sleep(0.01)
    second = store.ingest(_write(tmp_path / "two", {"renamed/y.bin": data}))
    after = os.stat(blob)
    assert first.entries[0].digest == second.entries[0].digest
    assert (after.st_ino, after.st_mtime_ns, after.st_nlink) == (
        before.st_ino, before.st_mtime_ns, before.st_nlink)
    assert os.stat(tmp_path / "two/renamed/y.bin").st_ino != before.st_ino  # left alone
    assert len([p for p in (store.root / "blobs").rglob("*") if p.is_file()]) == 1


@pytest.fixture
def other_filesystem(tmp_path: Path) -> Iterator[Path]:
    """A folder on a filesystem other than tmp_path's: a tmpfs this test mounts (as root),
    else /dev/shm when it is a different filesystem. A full run allows no skip, so a machine
    offering neither fails here."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(mnt)],
                             capture_output=True).returncode == 0
    if mounted:
        try:
            yield mnt
        finally:
            subprocess.run(["umount", str(mnt)], check=True)
        return
    shm = Path("/dev/shm")
    if not shm.is_dir() or os.stat(shm).st_dev == os.stat(tmp_path).st_dev:
        pytest.skip("needs root (to mount a tmpfs) or /dev/shm on another filesystem")
    folder = shm / f"osmo-test-{os.getpid()}-{time.monotonic_ns()}"
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def test_cross_filesystem_ingest_copies(tmp_path: Path, other_filesystem: Path) -> None:
    store = ArtifactStore(tmp_path / "artifacts")
    src = other_filesystem / "out"
    assert os.stat(other_filesystem).st_dev != os.stat(store.root).st_dev
    try:
        data = os.urandom((1 << 20) + 5)
        _write(src, {"d/x.bin": data, "e": b""})
        m = store.ingest(src)
        assert [(e.path, e.digest) for e in m.entries] == [("d/x.bin", _digest(data)),
                                                         ("e", _digest(b""))]
        blob = store.path(_digest(data))
        assert os.stat(blob).st_ino != os.stat(src / "d/x.bin").st_ino
        assert stat.S_IMODE(os.stat(blob).st_mode) == 0o444
        assert store.read(_digest(data)) == data
        assert not list((store.root / "tmp").iterdir())  # the temp copy was renamed away
        (src / "d/x.bin").write_bytes(b"changed")  # the source stays writable: it was copied
        assert store.verify(_digest(data))
    finally:
        shutil.rmtree(src, ignore_errors=True)


def test_corrupted_blob_is_never_used(store: ArtifactStore, tmp_path: Path) -> None:
    good, bad = os.urandom(5000), os.urandom(7000)
    m = store.ingest(_write(tmp_path / "out", {"a/good": good, "z/bad": bad}))
    _corrupt(store, _digest(bad))
    assert not store.verify(_digest(bad)) and store.verify(_digest(good))
    with pytest.raises(ArtifactCorrupted) as info:
        store.read(_digest(bad))
    assert info.value.digest == _digest(bad) and info.value.path == str(store.path(_digest(bad)))
    assert info.value.exit_code == 3 and _digest(bad) in str(info.value)
    dest = tmp_path / "dest"
    with pytest.raises(ArtifactCorrupted, match=_digest(bad)):
        store.materialize(m, dest)
    assert list(dest.iterdir()) == []  # not even the good file, nor staging leftovers


def test_missing_blob_is_reported(store: ArtifactStore, tmp_path: Path) -> None:
    m = store.ingest(_write(tmp_path / "out", {"f": b"gone"}))
    store.path(_digest(b"gone")).unlink()
    assert not store.has(_digest(b"gone")) and not store.verify(_digest(b"gone"))
    with pytest.raises(ArtifactCorrupted, match="is missing"):
        store.read(_digest(b"gone"))
    with pytest.raises(ArtifactCorrupted, match="is missing"):
        store.materialize(m, tmp_path / "dest")


def test_reingest_replaces_a_blob_of_the_wrong_size(store: ArtifactStore,
                                                    tmp_path: Path) -> None:
    store.ingest(_write(tmp_path / "one", {"f": b"content"}))
    blob = store.path(_digest(b"content"))
    blob.unlink()
    blob.write_bytes(b"torn")  # e.g. a power cut before the data reached the disk
    store.ingest(_write(tmp_path / "two", {"f": b"content"}))
    assert store.read(_digest(b"content")) == b"content"


def test_materialize_all_and_only(store: ArtifactStore, tmp_path: Path) -> None:
    m = store.ingest(_write(tmp_path / "out", FILES))
    dest = tmp_path / "dest"
    written = store.materialize(m, dest)
    assert written == [dest / e.path for e in m.entries]
    for rel, data in FILES.items():
        assert (dest / rel).read_bytes() == data
        assert os.stat(dest / rel).st_ino != os.stat(tmp_path / "out" / rel).st_ino
    assert sorted(p.name for p in dest.iterdir()) == ["a", "empty", "sp ace", "top.txt"]
    one = tmp_path / "one"
    assert store.materialize(m, one, only="a/b/c/deep.bin") == [one / "a/b/c/deep.bin"]
    assert [p.relative_to(one).as_posix() for p in one.rglob("*") if p.is_file()] == [
        "a/b/c/deep.bin"]
    with pytest.raises(NotFoundError, match="no artifact 'nope'"):
        store.materialize(m, one, only="nope")


def test_materialize_replaces_existing_files(store: ArtifactStore, tmp_path: Path) -> None:
    m = store.ingest(_write(tmp_path / "out", {"f": b"new"}))
    dest = _write(tmp_path / "dest", {"f": b"old content", "other": b"kept"})
    store.materialize(m, dest)
    assert (dest / "f").read_bytes() == b"new" and (dest / "other").read_bytes() == b"kept"


def test_gc_removes_only_unreferenced_blobs_past_grace(store: ArtifactStore,
                                                       tmp_path: Path) -> None:
    keep = store.ingest(_write(tmp_path / "keep", {"k": b"keep me"}))
    drop = store.ingest(_write(tmp_path / "drop", {"d": b"drop me!"}))
    referenced = {e.digest for e in keep.entries}
    assert store.gc(referenced) == (0, 0)  # everything is younger than the grace period
    assert store.gc(referenced, grace=10, now=time.time() + 5) == (0, 0)
    assert store.gc(referenced, grace=10, now=time.time() + 20) == (1, len(b"drop me!"))
    assert store.has(keep.entries[0].digest) and not store.has(drop.entries[0].digest)
    assert store.gc(set(), grace=0, now=time.time() + 1) == (1, len(b"keep me"))


def test_gc_grace_counts_from_ingest_not_file_mtime(store: ArtifactStore,
                                                    tmp_path: Path) -> None:
    out = _write(tmp_path / "out", {"old": b"written long ago"})
    os.utime(out / "old", (time.time() - 86400, time.time() - 86400))
    m = store.ingest(out)
    assert store.gc(set(), grace=60) == (0, 0)
    assert store.has(m.entries[0].digest)


def test_dedup_refreshes_grace(store: ArtifactStore, tmp_path: Path) -> None:
    m = store.ingest(_write(tmp_path / "one", {"f": b"x"}))
    blob = store.path(m.entries[0].digest)
    time.sleep(0.05)
    old_ctime = os.stat(blob).st_ctime_ns
    store.ingest(_write(tmp_path / "two", {"f": b"x"}))
    assert os.stat(blob).st_ctime_ns > old_ctime


def test_gc_removes_stale_temp_files(store: ArtifactStore) -> None:
    (store.root / "tmp" / "leftover").write_bytes(b"partial copy")
    assert store.gc(set()) == (0, 0)
    assert (store.root / "tmp" / "leftover").exists()
    store.gc(set(), grace=60, now=time.time() + 120)
    assert not (store.root / "tmp" / "leftover").exists()


def test_gc_refuses_malformed_digests(store: ArtifactStore) -> None:
    with pytest.raises(UsageError):
        store.gc({"sha256:nothex"})


def test_concurrent_ingests_of_identical_content(store: ArtifactStore, tmp_path: Path) -> None:
    data = {"same.bin": os.urandom(2 << 20), "small": b"tiny", "e": b""}
    folders = [_write(tmp_path / f"out{i}", data) for i in range(8)]
    results: list[Manifest] = []
    errors: list[BaseException] = []
    barrier = threading.Barrier(len(folders))

    def run(folder: Path) -> None:
        barrier.wait()
        try:
            results.append(store.ingest(folder))
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(f,)) for f in folders]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert len({m.digest for m in results}) == 1 and len(results) == 8
    for content in data.values():
        assert store.read(_digest(content)) == content
    assert len([p for p in (store.root / "blobs").rglob("*") if p.is_file()]) == 3
    assert not list((store.root / "tmp").iterdir())


def test_symlinks_inside_the_folder_are_followed(store: ArtifactStore, tmp_path: Path) -> None:
    out = _write(tmp_path / "out", {"ckpt/005/model.bin": b"weights", "data.txt": b"d"})
    (out / "ckpt" / "last").symlink_to("005")  # a folder link, as training loops write
    (out / "alias.txt").symlink_to(out / "data.txt")
    m = store.ingest(out)
    assert [(e.path, e.digest) for e in m.entries] == [
        ("alias.txt", _digest(b"d")), ("ckpt/005/model.bin", _digest(b"weights")),
        ("ckpt/last/model.bin", _digest(b"weights")), ("data.txt", _digest(b"d"))]
    dest = tmp_path / "dest"
    store.materialize(m, dest)
    assert not (dest / "ckpt" / "last").is_symlink()
    assert (dest / "ckpt" / "last" / "model.bin").read_bytes() == b"weights"


@pytest.mark.parametrize("make, message", [
    (lambda out, tmp: (out / "leak").symlink_to(tmp / "secret"), "outside the output folder"),
    (lambda out, tmp: (out / "leak").symlink_to("../secret"), "outside the output folder"),
    (lambda out, tmp: (out / "dangling").symlink_to("nowhere"), "dangling symlink"),
    (lambda out, tmp: (out / "sub" / "up").symlink_to(".."), "loops back"),
    (lambda out, tmp: (out / "self").symlink_to("."), "loops back"),
    (lambda out, tmp: os.mkfifo(out / "fifo"), "not a regular file"),
])
def test_unsafe_entries_reject_the_output(store: ArtifactStore, tmp_path: Path, make,  # type: ignore[no-untyped-def]
                                          message: str) -> None:
    (tmp_path / "secret").write_bytes(b"host file")
    out = _write(tmp_path / "out", {"sub/f": b"f"})
    make(out, tmp_path)
    with pytest.raises(OutputRejected, match=message) as info:
        store.ingest(out)
    assert info.value.exit_code == 1
    assert not store.has(_digest(b"host file")) and not store.has(_digest(b"f"))


def test_large_files_hashed_in_parallel_give_the_same_manifest(store: ArtifactStore,
                                                               tmp_path: Path) -> None:
    files = {f"big{i}.bin": os.urandom(5 << 20) for i in range(3)} | {"s/small": b"s"}
    m = store.ingest(_write(tmp_path / "out", files))  # 3 files over the pool threshold
    assert [(e.path, e.digest, e.size) for e in m.entries] == sorted(
        (p, _digest(d), len(d)) for p, d in files.items())
    assert all(store.verify(e.digest) for e in m.entries)


def test_limits_are_checked_before_anything_is_stored(store: ArtifactStore,
                                                      tmp_path: Path) -> None:
    out = _write(tmp_path / "out", {"a": b"x" * 600, "b": b"y" * 600})
    with pytest.raises(OutputRejected, match="1200 bytes in 2 files, more than .* 1000 bytes"):
        store.ingest(out, max_bytes=1000)
    with pytest.raises(OutputRejected, match="more than 1 files"):
        store.ingest(out, max_files=1)
    assert not [p for p in (store.root / "blobs").rglob("*") if p.is_file()]
    assert len(store.ingest(out, max_bytes=1200, max_files=2).entries) == 2


def test_a_tree_of_symlinks_that_lists_itself_is_bounded(store: ArtifactStore,
                                                         tmp_path: Path) -> None:
    out = tmp_path / "out"
    for level in range(30):  # d0 → d1 twice → d2 twice ...: 2**30 names for one file
        (out / f"d{level}").mkdir(parents=True)
        for link in ("l1", "l2"):
            (out / f"d{level}" / link).symlink_to(f"../d{level + 1}")
    (out / "d30").mkdir()
    (out / "d30" / "f").write_bytes(b"one file")
    with pytest.raises(OutputRejected, match="more than 1000 files"):
        store.ingest(out, max_files=1000)
