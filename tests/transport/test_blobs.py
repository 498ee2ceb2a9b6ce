"""Blob transfer over real zenoh sessions on loopback: verified, resumable, deduplicated."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from osmo.artifacts import ArtifactStore
from osmo.config import free_port
from osmo.transport import blobs
from osmo.transport.blobs import BlobServer, SameHost, TransferError, fetch_blob, fetch_manifest
from osmo.transport.rpc import ApiClient, ApiServer, ServerAsker, ask_back, gate_opener
from osmo.transport.zenoh_link import Link
from tests.transport.conftest import OTHER, TOKEN, Gate, Sealed


@pytest.fixture
def router() -> Iterator[tuple[Link, str, Gate]]:
    """A router session answering hellos, and the endpoint other processes connect to."""
    endpoint = f"tcp/127.0.0.1:{free_port(0)}"
    link = Link.router([endpoint])
    gate = Gate()
    api = ApiServer(link, lambda verb, request, who: {}, gate)
    yield link, endpoint, gate
    api.close()
    link.close()


def _store_with(tmp: Path, name: str, data: bytes) -> tuple[ArtifactStore, str]:
    src = tmp / f"{name}-src"
    src.mkdir()
    (src / "f").write_bytes(data)
    store = ArtifactStore(tmp / name)
    manifest = store.ingest(src)
    return store, manifest.entries[0].digest


def test_fetch_is_verified_and_counted(links: tuple[Link, Link], sealed: Sealed,
                                       tmp_path: Path) -> None:
    data = os.urandom(3 * blobs.CHUNK + 123)
    sender, digest = _store_with(tmp_path, "a", data)
    server = BlobServer(links[0], "server", sender, gate_opener(sealed.gate))
    receiver = ArtifactStore(tmp_path / "b")
    assert fetch_blob(sealed.api, "server", digest, len(data), receiver) == len(data)
    assert receiver.read(digest) == data
    assert fetch_blob(sealed.api, "server", digest, len(data), receiver) == 0  # has it
    server.close()


# A sender in its own process: a client session serving one store, as a remote worker does.
# A sender in its own process: a client session serving one store on its channel, as a remote
# worker does; it prints the channel's id, on which the server asks it.
_SENDER = """
import sys
from pathlib import Path
from osmo.artifacts import ArtifactStore
from osmo.transport.blobs import BlobServer
from osmo.transport.rpc import ApiClient
from osmo.transport.zenoh_link import Link
link = Link.client([sys.argv[1]])
api = ApiClient(link, token=sys.argv[3])
BlobServer(link, "sender", ArtifactStore(Path(sys.argv[2])), api.open_asked)
print(api.channel().id.hex(), flush=True)
sys.stdin.read()  # until the test closes stdin, or kills this process
"""


@contextmanager
def _sender(router: tuple[Link, str, Gate], store: ArtifactStore,
            digest: str) -> Iterator[tuple[subprocess.Popen[str], ServerAsker]]:
    """A sender process serving ``store`` as ``sender``, once its queryable answers."""
    link, endpoint, gate = router
    proc = subprocess.Popen([sys.executable, "-c", _SENDER, endpoint, str(store.root), TOKEN],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        asker = ask_back(link, gate, bytes.fromhex(proc.stdout.readline().strip()))
        assert asker is not None
        key = f"blob/sender/{digest.split(':')[1]}"
        deadline = time.monotonic() + 10
        while asker.answer(asker.ask(key, b"0:1", timeout=1.0)) is None:  # declared yet?
            assert time.monotonic() < deadline, "the sender never answered"
        yield proc, asker
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)
        assert proc.stdout is not None and proc.stdin is not None
        proc.stdout.close()
        proc.stdin.close()


def test_an_interrupted_fetch_resumes(router: tuple[Link, str, Gate], tmp_path: Path) -> None:
    """A transfer cut by the sender's death (SIGKILL mid-way) resumes from a new sender, and
    only the bytes missing are sent again."""
    size = 64 * blobs.CHUNK  # 32 MiB
    data = os.urandom(size)
    sender, digest = _store_with(tmp_path, "a", data)
    receiver = ArtifactStore(tmp_path / "b")
    partial = receiver.tmp / f"{digest.split(':')[1]}.partial"
    with _sender(router, sender, digest) as (proc, asker):
        got = 0

        def cut(n: int) -> None:  # the sender dies once an eighth has arrived
            nonlocal got
            got += n
            if got >= size // 8 and proc.poll() is None:
                proc.send_signal(signal.SIGKILL)
                proc.wait()

        t0 = time.monotonic()
        with pytest.raises(TransferError, match="no answer"):
            fetch_blob(asker, "sender", digest, size, receiver, on_bytes=cut)
        assert time.monotonic() - t0 < blobs._TIMEOUT, "a dead sender is noticed at once"
    kept = partial.stat().st_size
    assert size // 8 <= kept < size, "the transfer was cut mid-way"
    assert partial.read_bytes() == data[:kept], "what arrived is kept, in order"
    assert not receiver.has(digest)
    with _sender(router, sender, digest) as (_proc, asker):
        resent: list[int] = []
        sent = fetch_blob(asker, "sender", digest, size, receiver, on_bytes=resent.append)
    assert sum(resent) == sent == size - kept, "only the missing bytes crossed again"
    assert receiver.read(digest) == data and not partial.exists()


def test_damaged_bytes_are_never_published(links: tuple[Link, Link], sealed: Sealed,
                                           tmp_path: Path) -> None:
    data = os.urandom(2 * blobs.CHUNK)
    sender, digest = _store_with(tmp_path, "a", data)
    receiver = ArtifactStore(tmp_path / "b")
    partial = receiver.tmp / f"{digest.split(':')[1]}.partial"
    partial.write_bytes(b"x" * 100)  # garbage left by someone else
    server = BlobServer(links[0], "server", sender, gate_opener(sealed.gate))
    with pytest.raises(TransferError, match="does not match"):
        fetch_blob(sealed.api, "server", digest, len(data), receiver)
    assert not receiver.has(digest) and not partial.exists()
    # the next attempt starts clean and succeeds
    fetch_blob(sealed.api, "server", digest, len(data), receiver)
    assert receiver.read(digest) == data
    server.close()


def test_missing_blob_or_gone_peer(links: tuple[Link, Link], sealed: Sealed,
                                   tmp_path: Path) -> None:
    sender = ArtifactStore(tmp_path / "a")
    receiver = ArtifactStore(tmp_path / "b")
    server = BlobServer(links[0], "server", sender, gate_opener(sealed.gate))
    digest = "sha256:" + hashlib.sha256(b"nobody has this").hexdigest()
    with pytest.raises(TransferError, match="lacks the blob"):
        fetch_blob(sealed.api, "server", digest, 15, receiver)
    server.close()
    with pytest.raises(TransferError):
        fetch_blob(sealed.api, "nobody", digest, 15, receiver)


def test_same_host_links_instead_of_sending(sealed: Sealed, tmp_path: Path) -> None:
    data = os.urandom(10_000)
    sender, digest = _store_with(tmp_path, "a", data)
    receiver = ArtifactStore(tmp_path / "b")
    src = tmp_path / "m"
    src.mkdir()
    (src / "f").write_bytes(data)
    manifest = sender.ingest(src)
    sent = fetch_manifest(sealed.api, "nobody-needed", manifest, receiver,
                          same_host=SameHost(sender.root))
    assert sent == 0
    assert receiver.path(digest).stat().st_ino == sender.path(digest).stat().st_ino


class Unsealed:
    """An asker that sends its queries in clear with a chosen attachment (a thief)."""

    def __init__(self, link: Link, attachment: bytes | None) -> None:
        self._link, self._att = link, attachment

    def ask(self, rel: str, payload: bytes, *, timeout: float | None = None) -> object:
        return self._link.ask(self._link.key(rel), payload, attachment=self._att,
                              timeout=timeout or 5)

    def answer(self, pending: object) -> tuple[bool, bytes] | None:
        return next(((False, p) for p, _a in Link.replies(pending)), None)


def test_a_blob_server_answers_only_whom_it_allows(links: tuple[Link, Link], sealed: Sealed,
                                                   tmp_path: Path) -> None:
    sender, digest = _store_with(tmp_path, "a", b"for alice only\n")
    server = BlobServer(links[0], "worker", sender, gate_opener(sealed.gate),
                        lambda who, _digest: who is not None and who.name == "alice")
    try:
        bob = ApiClient(links[1], token=OTHER, timeout=5)
        for thief in (Unsealed(links[1], None), Unsealed(links[1], b"\x01" * 26), bob):
            with pytest.raises(TransferError):
                fetch_blob(thief, "worker", digest, 15, ArtifactStore(tmp_path / "thief"))
        receiver = ArtifactStore(tmp_path / "alice")
        assert fetch_blob(sealed.api, "worker", digest, 15, receiver) == 15
        assert receiver.path(digest).read_bytes() == b"for alice only\n"
    finally:
        server.close()
