"""``osmo.runtime.process.ports``: which ports a task's processes listen on, from ``/proc``."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator

import pytest

from osmo.config import free_port
from osmo.runtime.process.ports import task_listener, task_pids

# a parent that starts a child; the child listens (TCP on 127.0.0.2, UDP on 127.0.0.1)
CHILD = """
import socket, sys, time
t = socket.socket(); t.bind(("127.0.0.2", int(sys.argv[1]))); t.listen()
u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); u.bind(("127.0.0.1", int(sys.argv[2])))
print("ready", flush=True); time.sleep(600)
"""
PARENT = f"""
import subprocess, sys
child = subprocess.Popen([sys.executable, "-c", {CHILD!r}, *sys.argv[1:]])
child.wait()
"""


@pytest.fixture
def task() -> Iterator[tuple[subprocess.Popen[str], int, int]]:
    tcp, udp = free_port(0), free_port(0)
    proc = subprocess.Popen([sys.executable, "-c", PARENT, str(tcp), str(udp)],
                            stdout=subprocess.PIPE, text=True, start_new_session=True)
    assert proc.stdout is not None and proc.stdout.readline() == "ready\n"
    yield proc, tcp, udp
    for pid in task_pids(proc.pid):  # the ones this test started, by pid
        os.kill(pid, signal.SIGKILL)
    proc.wait(timeout=30)
    proc.stdout.close()


def test_a_childs_listener_is_the_tasks_at_the_address_it_is_bound_to(
        task: tuple[subprocess.Popen[str], int, int]) -> None:
    proc, tcp, udp = task
    assert len(task_pids(proc.pid)) == 2
    assert task_listener(proc.pid, tcp) == "127.0.0.2"
    assert task_listener(proc.pid, udp, udp=True) == "127.0.0.1"
    assert task_listener(proc.pid, udp) is None  # bound for UDP, not listening for TCP
    assert task_listener(proc.pid, tcp, udp=True) is None


def test_another_processs_listener_on_the_node_is_not_the_tasks(
        task: tuple[subprocess.Popen[str], int, int]) -> None:
    proc, tcp, _ = task
    with socket.socket() as outsider:  # this test process, outside the task's tree
        outsider.bind(("127.0.0.1", 0))
        outsider.listen()
        assert task_listener(proc.pid, outsider.getsockname()[1]) is None
        with socket.socket() as same_port:  # even on the port the task uses, elsewhere
            same_port.bind(("127.0.0.1", tcp))
            same_port.listen()
            assert task_listener(proc.pid, tcp) == "127.0.0.2"


def test_a_wildcard_bind_is_reached_on_loopback() -> None:
    with socket.socket(socket.AF_INET6) as six, socket.socket() as four:
        six.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
        six.bind(("::", 0))
        six.listen()
        four.bind(("0.0.0.0", 0))
        four.listen()
        assert task_listener(os.getpid(), four.getsockname()[1]) == "127.0.0.1"
        assert task_listener(os.getpid(), six.getsockname()[1]) == "::1"
