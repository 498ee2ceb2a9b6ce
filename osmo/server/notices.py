"""Change notices to clients, sent off the engine thread and coalesced.

The engine reports which workflows changed after each commit; clients waiting on a workflow
subscribe to ``events/<workflow_id>`` and re-read its state when a notice arrives. Sending a
zenoh message costs the engine thread most of a millisecond, so :class:`Notifier` hands the
ids to its own thread, which sends one notice per workflow for everything that piled up
meanwhile (a burst of changes becomes one notice).
"""

from __future__ import annotations

import threading

from osmo.transport.zenoh_link import Link

__all__ = ["Notifier"]


class Notifier:
    """Publishes ``{"workflow_id": ...}`` on ``events/<id>`` for changed workflows."""

    def __init__(self, link: Link) -> None:
        self._link = link
        self._pending: set[str] = set()
        self._cond = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="osmo-notices", daemon=True)
        self._thread.start()

    def changed(self, ids: set[str]) -> None:
        """Queue notices for ``ids`` (cheap; called by the engine after each commit)."""
        with self._cond:
            self._pending |= ids
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending or self._closed)
                if self._closed:
                    return
                ids, self._pending = self._pending, set()
            for wf_id in ids:
                self._link.publish(self._link.key("events", wf_id), {"workflow_id": wf_id})

    def close(self) -> None:
        """Send what is pending, then stop."""
        with self._cond:
            ids, self._pending = self._pending, set()
            self._closed = True
            self._cond.notify()
        for wf_id in ids:
            self._link.publish(self._link.key("events", wf_id), {"workflow_id": wf_id})
        self._thread.join(timeout=5)
