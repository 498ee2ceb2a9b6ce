"""Blob transfer over real zenoh sessions on loopback: verified, resumable, deduplicated."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.artifacts import ArtifactStore
from osmo.config import free_port
from osmo.transport import blobs
from osmo.transport.blobs import BlobServer, SameHost, TransferError, fetch_blob, fetch_manifest
from osmo.transport.zenoh_link import Link


@pytest.fixture
def links() -> Iterator[tuple[Link, Link]]:
    port = free_port(0)
    server = Link.router([f"tcp/127.0.0.1:{port}"])
    client = Link.client([f"tcp/127.0.0.1:{port}"])
    yield server, client
    client.close()
    server.close()


def _store_with(tmp: Path, name: str, data: bytes) -> tuple[ArtifactStore, str]:
    src = tmp / f"{name}-src"
    src.mkdir()
    (src / "f").write_bytes(data)
    store = ArtifactStore(tmp / name)
    manifest = store.ingest(src)
    return store, manifest.entries[0].digest


def test_fetch_is_verified_and_counted(links: tuple[Link, Link], tmp_path: Path) -> None:
    data = os.urandom(3 * blobs.CHUNK + 123)
    sender, digest = _store_with(tmp_path, "a", data)
    server = BlobServer(links[0], "server", sender)
    receiver = ArtifactStore(tmp_path / "b")
    assert fetch_blob(links[1], "server", digest, len(data), receiver) == len(data)
    assert receiver.read(digest) == data
    assert fetch_blob(links[1], "server", digest, len(data), receiver) == 0  # has it: no resend
    server.close()


def test_an_interrupted_fetch_resumes(links: tuple[Link, Link], tmp_path: Path) -> None:
    data = os.urandom(4 * blobs.CHUNK)
    sender, digest = _store_with(tmp_path, "a", data)
    receiver = ArtifactStore(tmp_path / "b")
    partial = receiver.tmp / f"{digest.split(':')[1]}.partial"
    partial.write_bytes(data[: 2 * blobs.CHUNK + 7])  # what a cut-off fetch left behind
    server = BlobServer(links[0], "server", sender)
    sent = fetch_blob(links[1], "server", digest, len(data), receiver)
    assert sent == len(data) - (2 * blobs.CHUNK + 7)
    assert receiver.read(digest) == data and not partial.exists()
    server.close()


def test_damaged_bytes_are_never_published(links: tuple[Link, Link], tmp_path: Path) -> None:
    data = os.urandom(2 * blobs.CHUNK)
    sender, digest = _store_with(tmp_path, "a", data)
    receiver = ArtifactStore(tmp_path / "b")
    partial = receiver.tmp / f"{digest.split(':')[1]}.partial"
    partial.write_bytes(b"x" * 100)  # garbage left by someone else
    server = BlobServer(links[0], "server", sender)
    with pytest.raises(TransferError, match="does not match"):
        fetch_blob(links[1], "server", digest, len(data), receiver)
    assert not receiver.has(digest) and not partial.exists()
    # the next attempt starts clean and succeeds
    fetch_blob(links[1], "server", digest, len(data), receiver)
    assert receiver.read(digest) == data
    server.close()


def test_missing_blob_or_gone_peer(links: tuple[Link, Link], tmp_path: Path) -> None:
    sender = ArtifactStore(tmp_path / "a")
    receiver = ArtifactStore(tmp_path / "b")
    server = BlobServer(links[0], "server", sender)
    digest = "sha256:" + hashlib.sha256(b"nobody has this").hexdigest()
    with pytest.raises(TransferError, match="lacks the blob"):
        fetch_blob(links[1], "server", digest, 15, receiver)
    server.close()
    with pytest.raises(TransferError):
        fetch_blob(links[1], "nobody", digest, 15, receiver)


def test_same_host_links_instead_of_sending(links: tuple[Link, Link], tmp_path: Path) -> None:
    data = os.urandom(10_000)
    sender, digest = _store_with(tmp_path, "a", data)
    receiver = ArtifactStore(tmp_path / "b")
    src = tmp_path / "m"
    src.mkdir()
    (src / "f").write_bytes(data)
    manifest = sender.ingest(src)
    sent = fetch_manifest(links[1], "nobody-needed", manifest, receiver,
                          same_host=SameHost(sender.root))
    assert sent == 0
    assert receiver.path(digest).stat().st_ino == sender.path(digest).stat().st_ino
