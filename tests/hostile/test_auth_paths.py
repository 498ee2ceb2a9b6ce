"""The server never reads a path a client chose, and trusts no same-host blob unhashed.

- A submitted spec naming a ``localpath`` (here: the server's own write-ahead log) is
  refused; so is the old ``source`` form that had the server render a client's file.
- A custom task type named with a client-chosen folder is never imported by the server.
- A same-host peer's blob whose bytes do not match its digest is not adopted (a clear
  ``ArtifactCorrupted``, naming the file and what it hashes to), and an upload pointing the
  server at a forged folder leaves nothing behind, so genuine content with that digest
  still gets in.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.artifacts import ArtifactStore
from osmo.artifacts.errors import ArtifactCorrupted
from osmo.config import host_id, read_server_info
from osmo.errors import UsageError
from osmo.layout import BlobDirs, Home
from osmo.transport.blobs import BlobServer, SameHost, fetch_blob
from osmo.transport.rpc import ApiClient, ApiServer, gate_opener
from osmo.transport.zenoh_link import Link
from tests.conftest import Osmo, write
from tests.transport.conftest import TOKEN, Gate

GENUINE = b"genuine bytes\n" * 1000
DIGEST = "sha256:" + hashlib.sha256(GENUINE).hexdigest()


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Osmo]:
    osmo = Osmo(tmp_path_factory.mktemp("paths") / "home")
    osmo("list", check=True)
    yield osmo
    osmo.stop_server()


@pytest.fixture
def api(server: Osmo) -> Iterator[ApiClient]:
    info = read_server_info(Home(server.home))
    assert info is not None
    link = Link.client([info.endpoint], info.cluster)
    token = server("token", "create", f"u{len(list(server.home.glob('*')))}{id(link)}",
                   "--role", "user", check=True).out.strip()
    yield ApiClient(link, timeout=20, token=token)
    link.close()


def _spec(files: list[dict]) -> dict:
    return {"workflow": {"name": "steal", "tasks": [
        {"name": "t", "command": ["cat", "/x/f"], "files": files}]}}


def test_a_localpath_to_the_servers_own_files_is_never_read(server: Osmo,
                                                            api: ApiClient) -> None:
    wal = server.home / "state.db-wal"
    assert wal.exists()
    with pytest.raises(UsageError, match="may not name a 'localpath'"):
        api.call("submit", {"spec": _spec([{"path": "/x/f", "localpath": str(wal)}])})
    text = f"workflow:\n  name: steal\n  tasks:\n  - name: t\n    command: [cat, /x/f]\n" \
           f"    files:\n    - path: /x/f\n      localpath: {wal}\n"
    with pytest.raises(UsageError, match="'source' is no longer accepted"):
        api.call("submit", {"source": {"path": "/x/wf.yaml", "text": text}})
    assert "steal" not in server("list", check=True).out


def test_a_localpath_of_the_client_is_read_by_the_client(server: Osmo, tmp_path: Path) -> None:
    write(tmp_path / "mine.txt", "the client-side file\n")
    spec = write(tmp_path / "wf.yaml", "workflow:\n  name: mine\n  tasks:\n  - name: t\n"
                 "    command: [cat, /x/f]\n    files:\n    - path: /x/f\n"
                 "      localpath: mine.txt\n")
    wf = server.submit(spec)
    assert "the client-side file" in server("spec", wf, check=True).out


def test_a_custom_type_from_a_client_named_folder_is_never_imported(
        server: Osmo, api: ApiClient, tmp_path: Path) -> None:
    marker = tmp_path / "imported"
    write(tmp_path / "evil_types.py", f"open({str(marker)!r}, 'w').write('ran')\n"
                                      "class T:\n    version = '1'\n")
    spec = {"workflow": {"name": "evil", "tasks": [{"name": "t", "type": "evil_types:T"}]}}
    with pytest.raises(Exception, match="not described by the client"):
        api.call("submit", {"spec": spec, "type_paths": [str(tmp_path)]})
    assert not marker.exists(), "the server imported code from a folder a client named"


def test_a_same_host_blob_is_hashed_before_it_is_adopted(tmp_path: Path) -> None:
    genuine = ArtifactStore(tmp_path / "genuine")
    src = write(tmp_path / "data" / "f.bin", "")
    src.write_bytes(GENUINE)
    assert genuine.ingest(src.parent).entries[0].digest == DIGEST
    forged = BlobDirs(tmp_path / "forged").blob(DIGEST[7:])
    forged.parent.mkdir(parents=True)
    forged.write_bytes(b"forged" * 100)
    receiver = ArtifactStore(tmp_path / "receiver")
    sock = f"unixsock-stream/{tmp_path}/s.sock"
    router = Link.router([sock], "blobs")
    client_link = Link.client([sock], "blobs")
    gate = Gate()
    api_server = ApiServer(router, lambda _verb, _request, _who: {}, gate)
    client = ApiClient(client_link, token=TOKEN, timeout=10)
    served = BlobServer(router, "peer", genuine, gate_opener(gate))
    try:
        with pytest.raises(ArtifactCorrupted, match="now hashes to"):
            fetch_blob(client, "peer", DIGEST, len(GENUINE), receiver,
                       same_host=SameHost(tmp_path / "forged"))
        assert not receiver.has(DIGEST), "the forged same-host file was adopted"
        assert not list(receiver.tmp.iterdir()), "nothing left behind"
        # over the network, the genuine bytes arrive
        assert fetch_blob(client, "peer", DIGEST, len(GENUINE), receiver) == len(GENUINE)
        assert receiver.path(DIGEST).read_bytes() == GENUINE
        # a same-host blob that does match is linked, not sent
        again = ArtifactStore(tmp_path / "again")
        assert fetch_blob(client, "peer", DIGEST, len(GENUINE), again,
                          same_host=SameHost(genuine.root)) == 0
        assert again.path(DIGEST).read_bytes() == GENUINE
    finally:
        served.close()
        api_server.close()
        client_link.close()
        router.close()


def test_an_upload_from_a_forged_same_host_folder_leaves_nothing(
        server: Osmo, api: ApiClient, tmp_path: Path) -> None:
    forged = BlobDirs(tmp_path / "forged").blob(DIGEST[7:])
    forged.parent.mkdir(parents=True)
    forged.write_bytes(b"forged" * 100)
    manifest = json.dumps({"version": 1, "entries": [
        {"path": "f.bin", "digest": DIGEST, "size": len(GENUINE)}]})
    host = host_id()  # this host's: the test runs beside the server
    with pytest.raises(Exception, match="now hashes to"):
        api.call("dataset_upload", {"name": "forged", "manifest": manifest, "source": {
            "owner": "client-nobody", "host_id": host, "artifacts": str(tmp_path / "forged"),
            "key": "00"}}, timeout=120)
    store = ArtifactStore(server.home / "artifacts")
    assert not store.has(DIGEST), "the server adopted a blob it never hashed"
    data = write(tmp_path / "real" / "f.bin", "")
    data.write_bytes(GENUINE)
    server("dataset", "upload", "genuine", str(data.parent), check=True)
    assert store.path(DIGEST).read_bytes() == GENUINE
