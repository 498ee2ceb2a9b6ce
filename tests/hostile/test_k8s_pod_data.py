"""A pod's data over zenoh (issue #28): the node's side (``podio``) against the pod's
(``podside``), real sessions on loopback, no cluster needed.

Attacks: a ticket replayed, a ticket of another attempt (or of the other role), an input
changed on its way, a collector that sends paths out of the output (``..``, absolute, a
symlink), an upload larger than the task's storage, outputs offered before the task ended,
a node restarted mid-collection (its collector's ticket served again from its digest only).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from osmo.config import free_port
from osmo.errors import NotAllowed, NotAuthenticated, UsageError
from osmo.runtime.kubernetes import podio, podside
from osmo.runtime.kubernetes.podio import CHUNK, COLLECT, FETCH, PodData, root_of, scan_mounts
from osmo.transport.auth import token_digest
from osmo.transport.rpc import ApiClient
from osmo.transport.zenoh_link import Link
from tests.conftest import REPO

NODE = "kube-node"


@dataclass
class Bus:
    node: PodData
    pod: Link
    endpoint: str
    router: Link

    def client(self, ticket: str) -> ApiClient:
        return ApiClient(self.pod, timeout=5.0, token=ticket, root=root_of(NODE))


@pytest.fixture
def bus() -> Iterator[Bus]:
    endpoint = f"tcp/127.0.0.1:{free_port(0)}"
    router = Link.router([endpoint])
    node = PodData(router, NODE)
    pod = Link.client([endpoint])
    yield Bus(node, pod, endpoint, router)
    pod.close()
    node.stop()
    router.close()


def _attempt(bus: Bus, tmp: Path, name: str, *, max_bytes: int | None = None
             ) -> tuple[dict[str, str], Path, Path]:
    """An attempt served by the node: its tickets, its node folder and its output folder."""
    src = tmp / name
    (src / "in0" / "sub").mkdir(parents=True)
    (src / "in0" / "a.txt").write_text(f"input of {name}\n")
    (src / "in0" / "sub" / "b.bin").write_bytes(os.urandom(600_000))
    (src / "config.txt").write_text("cfg\n")
    output = tmp / f"{name}-output.partial"
    output.mkdir()
    files, dirs = scan_mounts([(src / "in0", "osmo/data/input/0"),
                               (src / "config.txt", "etc/x/config.txt")])
    tickets = bus.node.open(name, files, [*dirs, podside.OUTPUT], output, max_bytes=max_bytes)
    return tickets, src, output


def test_the_init_container_fetches_every_file_checked(bus: Bus, tmp_path: Path) -> None:
    tickets, src, _ = _attempt(bus, tmp_path, "a1")
    root = tmp_path / "pod"
    root.mkdir()
    podside.fetch(bus.client(tickets[FETCH]), "a1", root)
    assert (root / "osmo/data/input/0/a.txt").read_text() == "input of a1\n"
    assert (root / "osmo/data/input/0/sub/b.bin").read_bytes() == (
        src / "in0/sub/b.bin").read_bytes()
    assert (root / "etc/x/config.txt").read_text() == "cfg\n"
    assert (root / podside.OUTPUT).is_dir()


def test_an_input_changed_on_its_way_fails_the_fetch_naming_it(bus: Bus,
                                                               tmp_path: Path) -> None:
    tickets, src, _ = _attempt(bus, tmp_path, "a1")
    (src / "in0" / "a.txt").write_text("tampered after it was checked\n")
    root = tmp_path / "pod"
    root.mkdir()
    ticket = tmp_path / "ticket"
    ticket.write_text(tickets[FETCH])
    done = subprocess.run(
        [sys.executable, "-m", "osmo.runtime.kubernetes.podside", "fetch", "--connect",
         bus.endpoint, "--node", NODE, "--attempt", "a1", "--ticket", str(ticket),
         "--root", str(root)], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert done.returncode == 1, done
    assert "osmo/data/input/0/a.txt does not match its digest sha256:" in done.stderr, done
    assert "Traceback" not in done.stderr
    assert "does not match its digest" in (bus.node.fetch_failure("a1") or "")


def test_a_replayed_ticket_opens_nothing(bus: Bus, tmp_path: Path) -> None:
    tickets, _, _ = _attempt(bus, tmp_path, "a1")
    first = bus.client(tickets[FETCH])
    assert first.call("manifest", {"attempt": "a1"})["files"]
    with pytest.raises(NotAuthenticated, match="does not know this token"):
        bus.client(tickets[FETCH]).call("manifest", {"attempt": "a1"})
    bus.node.close("a1")  # the attempt ended: its open channel acts no more either
    with pytest.raises(NotAuthenticated):
        first.call("manifest", {"attempt": "a1"})


def test_a_ticket_acts_for_its_own_attempt_and_role_only(bus: Bus, tmp_path: Path) -> None:
    mine, _, _ = _attempt(bus, tmp_path, "a1")
    _attempt(bus, tmp_path, "b2")
    fetcher = bus.client(mine[FETCH])
    with pytest.raises(NotAllowed, match="this ticket is for attempt a1, not b2"):
        fetcher.call("manifest", {"attempt": "b2"})
    with pytest.raises(NotAllowed, match="may not ask 'offer'"):
        fetcher.call("offer", {"attempt": "a1", "files": []})
    collector = bus.client(mine[COLLECT])
    with pytest.raises(NotAllowed, match="may not ask 'read'"):
        collector.call("read", {"attempt": "a1", "index": 0, "offset": 0})


def test_outputs_come_back_whole_after_the_task_ended(bus: Bus, tmp_path: Path) -> None:
    tickets, _, output = _attempt(bus, tmp_path, "a1")
    root = tmp_path / "pod"
    (root / podside.OUTPUT / "deep" / "er").mkdir(parents=True)
    (root / podside.OUTPUT / "deep" / "er" / "x.bin").write_bytes(os.urandom(700_000))
    (root / podside.OUTPUT / "empty").write_bytes(b"")
    os.symlink("deep/er/x.bin", root / podside.OUTPUT / "inside-link")
    collector = bus.client(tickets[COLLECT])
    with pytest.raises(NotAllowed, match="only after the task's container ended"):
        collector.call("offer", {"attempt": "a1", "files": []})
    bus.node.ended("a1", collect=True)
    podside.collect(collector, "a1", root)
    assert bus.node.collected("a1", 5) is None
    data = (root / podside.OUTPUT / "deep/er/x.bin").read_bytes()
    assert (output / "deep/er/x.bin").read_bytes() == data
    assert (output / "inside-link").read_bytes() == data  # followed inside, as ingest does
    assert (output / "empty").read_bytes() == b""


@pytest.mark.parametrize("name", ["../escaped", "/etc/escaped", "a/../../escaped", "a//b",
                                  "./a", "a/\0b"])
def test_a_collector_cannot_write_outside_the_output(bus: Bus, tmp_path: Path,
                                                     name: str) -> None:
    tickets, _, output = _attempt(bus, tmp_path, "a1")
    bus.node.ended("a1", collect=True)
    collector = bus.client(tickets[COLLECT])
    with pytest.raises(UsageError, match="the output was refused"):
        collector.call("offer", {"attempt": "a1", "files": [{"path": name, "size": 1}]})
    assert "the output was refused" in (bus.node.collected("a1", 5) or "")
    assert not (tmp_path / "escaped").exists() and list(output.iterdir()) == []


def test_a_symlink_out_of_the_output_is_never_sent(bus: Bus, tmp_path: Path) -> None:
    tickets, _, output = _attempt(bus, tmp_path, "a1")
    root = tmp_path / "pod"
    (root / podside.OUTPUT).mkdir(parents=True)
    secret = tmp_path / "host-secret"
    secret.write_text("not yours")
    os.symlink(secret, root / podside.OUTPUT / "loot")
    bus.node.ended("a1", collect=True)
    with pytest.raises(podside.DataError, match="outside the output folder"):
        podside.collect(bus.client(tickets[COLLECT]), "a1", root)
    assert list(output.iterdir()) == []


def test_an_oversize_upload_is_refused(bus: Bus, tmp_path: Path) -> None:
    tickets, _, output = _attempt(bus, tmp_path, "a1", max_bytes=1000)
    bus.node.ended("a1", collect=True)
    collector = bus.client(tickets[COLLECT])
    with pytest.raises(UsageError, match="more than the task's storage limit of 1000"):
        collector.call("offer", {"attempt": "a1", "files": [{"path": "a", "size": 600},
                                                            {"path": "b", "size": 600}]})
    # offered small, sent large: refused at the first byte beyond the offer
    tickets, _, output = _attempt(bus, tmp_path, "a2", max_bytes=1000)
    bus.node.ended("a2", collect=True)
    collector = bus.client(tickets[COLLECT])
    collector.call("offer", {"attempt": "a2", "files": [{"path": "a", "size": 4}]})
    with pytest.raises(UsageError, match="beyond the offered size"):
        collector.call("put", {"attempt": "a2", "index": 0, "offset": 0, "data": "eHh4eHh4"})
    assert "beyond its offered size" in (bus.node.collected("a2", 5) or "")


def test_a_failed_task_hands_nothing_back(bus: Bus, tmp_path: Path) -> None:
    tickets, _, output = _attempt(bus, tmp_path, "a1")
    root = tmp_path / "pod"
    (root / podside.OUTPUT).mkdir(parents=True)
    (root / podside.OUTPUT / "partial").write_text("half")
    bus.node.ended("a1", collect=False)
    assert podside.collect(bus.client(tickets[COLLECT]), "a1", root) == 0
    assert bus.node.collected("a1", 5) is not None
    assert list(output.iterdir()) == []


def _output(root: Path) -> dict[str, bytes]:
    """A collector's output of several chunks, in the pod's data volume under ``root``."""
    made = {"big.bin": os.urandom(3 * CHUNK + 17), "sub/small.txt": b"small\n"}
    for name, data in made.items():
        (root / podside.OUTPUT / name).parent.mkdir(parents=True, exist_ok=True)
        (root / podside.OUTPUT / name).write_bytes(data)
    return made


def _empty(folder: Path) -> None:
    for child in folder.iterdir():
        shutil.rmtree(child) if child.is_dir() else child.unlink()


def test_a_node_back_from_a_restart_gets_the_output_whole_from_a_waiting_collector(
        bus: Bus, tmp_path: Path) -> None:
    """Killed while the collector waited; the next life serves its ticket again from the
    journaled digest alone, and the collector (patient) sends everything once."""
    tickets, _, output = _attempt(bus, tmp_path, "a1")
    root = tmp_path / "pod"
    made = _output(root)
    collector = bus.client(tickets[COLLECT])
    assert collector.call("wait", {"attempt": "a1"}, timeout=15) == {"ended": False,
                                                                     "collect": False}
    bus.node.stop()  # killed: its channels and tickets die with it
    again = PodData(bus.router, NODE)
    try:
        again.reopen("a1", token_digest(tickets[COLLECT]), output)
        again.ended("a1", collect=True)
        assert podside.collect(collector, "a1", root, pause=0.1) == sum(map(len, made.values()))
        assert again.collected("a1", 5) is None
        assert {n: (output / n).read_bytes() for n in made} == made
        # the served-again ticket opened one channel; a second hello with it opens nothing
        with pytest.raises(NotAuthenticated):
            bus.client(tickets[COLLECT]).call("wait", {"attempt": "a1"})
    finally:
        again.stop()


def test_a_node_restarted_mid_upload_gets_the_output_again_whole(
        bus: Bus, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The node's memory is lost after the collector's first chunk (a new life: the ticket
    served again, the partial output emptied): the collector notices the new channel and
    sends the whole output again; nothing half is kept."""
    tickets, _, output = _attempt(bus, tmp_path, "a1")
    root = tmp_path / "pod"
    made = _output(root)
    put = podio._VERBS[(COLLECT, "put")]
    lives: list[str] = []

    def restarting_put(node: PodData, entry: Any, request: dict[str, Any]) -> Any:
        done = put(node, entry, request)
        if not lives:  # after the first chunk: the node "restarts"
            lives.append("restarted")
            node.close("a1")
            _empty(output)
            node.reopen("a1", token_digest(tickets[COLLECT]), output)
            node.ended("a1", collect=True)
        return done

    monkeypatch.setitem(podio._VERBS, (COLLECT, "put"), restarting_put)
    bus.node.ended("a1", collect=True)
    podside.collect(bus.client(tickets[COLLECT]), "a1", root, pause=0.1)
    assert lives == ["restarted"]
    assert bus.node.collected("a1", 5) is None
    assert {n: (output / n).read_bytes() for n in made} == made


def test_a_collector_gives_up_on_a_node_that_never_comes_back(bus: Bus,
                                                              tmp_path: Path) -> None:
    tickets, _, _ = _attempt(bus, tmp_path, "a1")
    root = tmp_path / "pod"
    _output(root)
    bus.node.stop()
    with pytest.raises(podside.ServerUnreachable):
        podside.collect(ApiClient(bus.pod, timeout=0.5, token=tickets[COLLECT],
                                  root=root_of(NODE)), "a1", root, patience=1.5, pause=0.2)
