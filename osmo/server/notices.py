"""Change notices to clients, sent off the engine thread and coalesced.

The engine reports which workflows changed after each commit; clients waiting on a workflow
subscribe to ``events/<workflow_id>`` and re-read its state when a notice arrives. Each
notice is signed with the server's key (``osmo.transport.seal.Signer``: its attachment is
the signature of the key and payload), so a client acts on no notice a peer made up. Sending a
zenoh message costs the engine thread most of a millisecond, so :class:`Notifier` hands the
ids to its own thread, which sends one notice per workflow for everything that piled up
meanwhile (a burst of changes becomes one notice).

After sending, the thread lets ``interval`` seconds pass before it sends again: the first
change after a quiet spell is told at once, and a busy workflow gets at most one notice per
interval, carrying every change since the last one. A change is never told more than
``interval`` late, and none is dropped: what is pending when the notifier closes is sent then.
A workflow's end is told at once, interval or not, and its notice says so (``"ended":
true``): a client waiting for it (``osmo submit --wait``) returns that much sooner.
"""

from __future__ import annotations

import json
import threading

from osmo.transport.seal import Signer
from osmo.transport.zenoh_link import Link

__all__ = ["NOTICE_INTERVAL", "Notifier"]

NOTICE_INTERVAL = 0.05
"""Seconds between two sends of notices (but for a workflow's end)."""


class Notifier:
    """Publishes ``{"workflow_id": ...}`` on ``events/<id>`` for changed workflows.

    Args:
        link: the server's zenoh link.
        signer: signs each notice.
        interval: seconds to wait after a send before the next (see the module docstring).
    """

    def __init__(self, link: Link, signer: Signer, interval: float = NOTICE_INTERVAL) -> None:
        self._link, self._signer = link, signer
        self._interval = interval
        self._pending: set[str] = set()
        self._cond = threading.Condition()
        self._closed = False
        self._idle = False  # the thread waits for changes (not out its interval)
        self._ended: set[str] = set()  # pending ends: sent without waiting out the interval
        self._thread = threading.Thread(target=self._run, name="osmo-notices", daemon=True)
        self._thread.start()

    def changed(self, ids: set[str], ended: set[str] | frozenset[str] = frozenset()) -> None:
        """Queue notices for ``ids`` (cheap; called by the engine after each commit).

        ``ended``: those of them that reached their end (told at once).
        """
        with self._cond:
            self._pending |= ids
            self._ended |= ended & ids
            if self._idle or self._ended:  # else, within its interval, it would only wait again
                self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                self._idle = True
                self._cond.wait_for(lambda: self._pending or self._closed)
                self._idle = False
                if self._closed:
                    return
                ids, ended = self._pending, self._ended
                self._pending, self._ended = set(), set()
            self._send(ids, ended)
            with self._cond:  # coalesce what changes meanwhile into the next send
                self._cond.wait_for(lambda: self._closed or bool(self._ended),
                                    timeout=self._interval)

    def _send(self, ids: set[str], ended: set[str]) -> None:
        for wf_id in ids:
            key = self._link.key("events", wf_id)
            notice: dict[str, object] = {"workflow_id": wf_id}
            if wf_id in ended:
                notice["ended"] = True
            payload = json.dumps(notice).encode()
            self._link.put(key, payload, self._signer.sign_notice(key, payload))

    def close(self) -> None:
        """Send what is pending, then stop."""
        with self._cond:
            ids, ended = self._pending, self._ended
            self._pending, self._ended = set(), set()
            self._closed = True
            self._cond.notify()
        self._send(ids, ended)
        self._thread.join(timeout=5)
