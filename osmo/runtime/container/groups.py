"""Container groups of one node: their networks, and their lead's start before its peers'.

When every member of a group runs at one address (this host), the group gets its own network
and ``{{host:NAME}}`` is NAME's alias on it (the task name). Members spread over several
hosts use the host's network and ``{{host:NAME}}`` stays NAME's address. A peer of a
networked group starts once the lead's container runs (the lead listens first, as in OSMO):
its start waits for the lead's on the engine's event stream.

A network is made with its group's first member here and removed with its last one; what a
crash leaves is removed by label (``ContainerRuntime.clean_orphans``).
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Mapping

from osmo.runtime.container.engine import ContainerEngine
from osmo.runtime.container.run import ContainerError, ContainerRun, safe_name
from osmo.scheduler.types import PrepareAttempt

__all__ = ["Groups", "alias"]

_ALIAS = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,62}")
_LEAD_WAIT = 30.0  # s: a peer waits this long for its lead's container, then starts anyway
_CLOCK_SLACK = 1.0  # s: events are stamped by the engine; read a little before the spawn


def alias(task: str) -> str:
    """A task's name on its group network: the name itself when the engine can take it."""
    return task if _ALIAS.fullmatch(task) else safe_name(task)[:63]


class Groups:
    """The group networks of one node's containers (thread-safe).

    Args:
        engine: the engine that makes and removes them.
        labels: the labels every network carries (its owner's).
    """

    def __init__(self, engine: ContainerEngine, labels: Mapping[str, str]) -> None:
        self.engine = engine
        self.labels = dict(labels)
        self._lock = threading.Lock()
        self._networks: dict[str, int] = {}  # network → attempts of this node using it
        self._leads: dict[str, threading.Event] = {}  # network → its lead was started
        self._lead_since: dict[str, float] = {}  # network → when its lead's CLI was spawned

    def network(self, cmd: PrepareAttempt) -> str | None:
        """The group's network: this owner's own, ``host`` (spread over hosts) or None."""
        if len(cmd.hosts) < 2:
            return None
        if len(set(cmd.hosts.values())) > 1:
            return "host"
        return safe_name(cmd.workflow_id, *sorted(cmd.hosts),
                         owner=self.labels.get("osmo.owner", ""))

    def hosts(self, cmd: PrepareAttempt) -> dict[str, str] | None:
        """``{{host:NAME}}`` of each member: its alias on the group's network (None: none)."""
        if self.network(cmd) is None:
            return None
        return {name: alias(name) for name in cmd.hosts}

    def join(self, network: str) -> None:
        """An attempt of this node joins ``network`` (made with the first).

        Raises:
            ContainerError: the network cannot be made.
        """
        with self._lock:
            count = self._networks.get(network, 0)
            self._networks[network] = count + 1
            if count:
                return
            try:
                self.engine.create_network(network, self.labels)
            except ContainerError:
                self._networks.pop(network, None)
                raise

    def started(self, run: ContainerRun, *, since: float | None = None) -> None:
        """Note that ``run``'s engine CLI was spawned (at ``since``, epoch seconds, or now).

        A lead releases its waiting peers, which then wait for its container's start.
        """
        if run.labels.get("osmo.lead") == "1" and run.network is not None:
            with self._lock:
                self._lead_since[run.network] = time.time() if since is None else since
            self._lead_event(run.network).set()

    def wait_for_lead(self, run: ContainerRun) -> None:
        """Block (I/O thread) until the lead of ``run``'s group network runs, at most 30 s.

        The start barrier starts a group's members together; a peer that calls its lead at
        once (OSMO's ``nc`` tutorial) needs the lead to be listening first. The wait is the
        engine's event stream (``ContainerEngine.wait_started``); only an engine without
        one is asked every 50 ms whether the lead runs.
        """
        if run.labels.get("osmo.lead") != "0" or run.network is None:
            return
        deadline = time.monotonic() + _LEAD_WAIT
        if not self._lead_event(run.network).wait(_LEAD_WAIT):
            return
        with self._lock:
            since = self._lead_since.get(run.network, time.time()) - _CLOCK_SLACK
        try:
            self.engine.wait_started(("osmo.network", run.network), ("osmo.lead", "1"),
                                     since=since, timeout=max(0.0, deadline - time.monotonic()))
        except ContainerError:
            self._poll_lead(run.network, deadline)

    def _poll_lead(self, network: str, deadline: float) -> None:
        lead = {**self.labels, "osmo.network": network, "osmo.lead": "1"}
        while time.monotonic() < deadline:
            try:
                if self.engine.running(lead):
                    return
            except ContainerError:
                return
            time.sleep(0.05)

    def left(self, run: ContainerRun) -> None:
        """An attempt that used ``run`` ended: its group network goes with its last member."""
        if run.network is None or run.network == "host" or "osmo.network" not in run.labels:
            return
        with self._lock:
            left = self._networks.get(run.network, 1) - 1
            if left > 0:
                self._networks[run.network] = left
                return
            self._networks.pop(run.network, None)
            self._leads.pop(run.network, None)
            self._lead_since.pop(run.network, None)
        try:
            self.engine.remove_network(run.network)
        except ContainerError:
            pass  # still in use elsewhere, or the engine failed: orphan clean-up takes it

    def close(self) -> None:
        """Remove the networks still in use here."""
        with self._lock:
            networks, self._networks = list(self._networks), {}
        for network in networks:
            try:
                self.engine.remove_network(network)
            except ContainerError:
                pass

    def _lead_event(self, network: str) -> threading.Event:
        with self._lock:
            return self._leads.setdefault(network, threading.Event())
