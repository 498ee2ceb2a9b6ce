"""The engine's inbox: one queue for executors' events and for requests from API threads.

It exists before the engine and its executors, so that neither needs the other to be built:
executors are given :meth:`Inbox.post` (and the hub :meth:`Inbox.ask`), the engine reads
what they send with :meth:`Inbox.take`. A request (``osmo.server.requests``) waits in
:meth:`Inbox.ask` for its answer, which the engine gives after the batch it was applied in
is committed. Once the engine stopped for good (:meth:`Inbox.close`), every request in the
queue, in hand or asked later gets an ``InfrastructureError``.
"""

from __future__ import annotations

import queue
from collections.abc import Iterable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

from osmo.errors import InfrastructureError
from osmo.scheduler.types import Event
from osmo.server.requests import Request

__all__ = ["STOP", "Asked", "Inbox"]

STOP = object()
"""Queued by ``Engine.stop``: finish what is in hand, then leave the loop."""

_MOST = 4096  # items taken at once: one batch of the engine's loop at the most


@dataclass
class Asked:
    """A request in the queue and where its answer goes."""

    request: Request
    future: Future[Any]


class Inbox:
    """Events and requests for the engine, in arrival order (thread-safe)."""

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._closed: str | None = None

    def post(self, event: Event) -> None:
        """Queue an event (cheap: executors call it from their own threads)."""
        self._queue.put(event)

    def ask(self, request: Request, timeout: float = 60) -> Any:
        """Queue ``request`` and wait for its answer (see ``osmo.server.requests``).

        Raises:
            OsmoError: what applying the request raised (nothing of it was committed).
            InfrastructureError: the engine stopped.
            TimeoutError: no answer within ``timeout`` seconds.
        """
        if self._closed is not None:
            raise InfrastructureError(f"the server's engine stopped: {self._closed}")
        future: Future[Any] = Future()
        self._queue.put(Asked(request, future))
        return future.result(timeout=timeout)

    def stop(self) -> None:
        """Ask the engine's loop to finish what it has in hand and leave."""
        self._queue.put(STOP)

    def take(self, timeout: float | None) -> list[Any]:
        """Wait for the first item, then take whatever else is queued by then.

        Waits up to ``timeout`` seconds (None: for ever); takes at most a few thousand items. Empty
        when none came.
        """
        try:
            items = [self._queue.get(timeout=timeout)]
        except queue.Empty:
            return []
        while len(items) < _MOST:
            try:
                items.append(self._queue.get_nowait())
            except queue.Empty:
                break
        return items

    def close(self, why: str, in_hand: Iterable[Any] = ()) -> None:
        """The engine cannot go on: fail every request with ``why``.

        Those in ``in_hand``, in the queue, and asked from now on.
        """
        self._closed = why
        error = InfrastructureError(f"the server's engine stopped: {why}")
        pending = list(in_hand)
        while True:
            try:
                pending.append(self._queue.get_nowait())
            except queue.Empty:
                break
        for item in pending:
            if isinstance(item, Asked) and not item.future.done():
                item.future.set_exception(error)
