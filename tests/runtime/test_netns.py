"""A node's network namespace (real keeper, real slirp4netns): what starting it leaves alone."""

from __future__ import annotations

import os
import socket
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.runtime.process.sandbox import node_network
from tests.runtime.churn import _MS_BIND, _mount, _umount

_MS_SHARED = 1 << 20


@pytest.fixture
def shared_mount() -> Iterator[Path]:
    """A shared mount with a mount inside, as podman's /run/netns holds its namespaces."""
    if os.geteuid() != 0:
        pytest.skip("making mounts needs root")
    top = Path(tempfile.mkdtemp(prefix="osmo-netns-", dir="/run"))
    inner = top / "inner"
    inner.mkdir()
    assert _mount(str(top), str(top), None, _MS_BIND) == 0
    try:
        assert _mount("none", str(top), None, _MS_SHARED) == 0
        assert _mount("none", str(inner), "tmpfs", 0) == 0
        yield inner
    finally:
        _umount(str(inner))
        _umount(str(top))
        inner.rmdir()
        top.rmdir()


def test_starting_a_node_network_unmounts_nothing_on_the_host(shared_mount: Path) -> None:
    """slirp4netns' own sandbox unmounts its old root after making only / private: in the
    host's mount namespace, or one that shares its mounts, that unmount reaches the host."""
    network = node_network()
    try:
        assert not network.caveat, network.caveat  # slirp4netns is running
        time.sleep(0.5)  # its sandbox is made after it reports ready
        assert os.path.ismount(shared_mount), "starting the node's network unmounted it"
    finally:
        network.close()
    assert os.path.ismount(shared_mount)


def test_a_socket_of_the_node_network_reaches_its_loopback_not_the_hosts() -> None:
    with socket.socket() as host:
        host.bind(("127.0.0.1", 0))
        host.listen()
        network = node_network(outbound=False)
        try:
            made = network.socket(socket.AF_INET, socket.SOCK_STREAM)
            with made, pytest.raises(ConnectionRefusedError):
                made.connect(host.getsockname())
        finally:
            network.close()
