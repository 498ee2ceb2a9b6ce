"""A minimal event loop on one thread: readable fds, calls from other threads, timers.

The worker pool runs every process-related action on this thread, so attempt state needs no
locks: other threads only ``call_soon`` (a queue plus an ``eventfd`` wake-up). Waiting is
``selector.select(timeout)`` with the timeout of the next timer; nothing polls.

It must not know about attempts or processes; callbacks carry the meaning.
"""

from __future__ import annotations

import collections
import heapq
import itertools
import logging
import os
import selectors
import threading
import time
from collections.abc import Callable
from typing import Any

__all__ = ["Reactor", "Timer"]

_log = logging.getLogger(__name__)

Callback = Callable[..., Any]


class Timer:
    """A scheduled call; ``cancel()`` before it fires to drop it."""

    __slots__ = ("when", "callback", "args", "cancelled")

    def __init__(self, when: float, callback: Callback, args: tuple[Any, ...]) -> None:
        self.when = when
        self.callback = callback
        self.args = args
        self.cancelled = False

    def cancel(self) -> None:
        """Do not run this timer."""
        self.cancelled = True


class Reactor:
    """One daemon thread driving a selector, a thread-safe call queue and timers."""

    def __init__(self, name: str) -> None:
        self._selector = selectors.DefaultSelector()
        self._wake_fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        self._selector.register(self._wake_fd, selectors.EVENT_READ, self._drain_wake)
        self._calls: collections.deque[tuple[Callback, tuple[Any, ...]]] = collections.deque()
        self._timers: list[tuple[float, int, Timer]] = []
        self._seq = itertools.count()
        self._stopping = False
        self._closed = False
        self._lock = threading.Lock()  # guards the wake-up fd against use after close
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    # -------------------------------------------------------------- any thread

    def call_soon(self, callback: Callback, *args: Any) -> None:
        """Run ``callback(*args)`` on the reactor thread, in call order."""
        with self._lock:
            if self._closed:
                return  # stopped: nothing will run any more
            self._calls.append((callback, args))
            os.eventfd_write(self._wake_fd, 1)

    def stop(self, final: Callback | None = None) -> None:
        """Run ``final()`` on the reactor thread, stop it and wait for it (idempotent)."""
        if self._thread.is_alive():
            self.call_soon(self._stop, final)
            if threading.current_thread() is not self._thread:
                self._thread.join()

    # -------------------------------------------------------------- reactor thread only

    def call_later(self, delay: float, callback: Callback, *args: Any) -> Timer:
        """Run ``callback(*args)`` after ``delay`` seconds (reactor thread only)."""
        timer = Timer(time.monotonic() + delay, callback, args)
        heapq.heappush(self._timers, (timer.when, next(self._seq), timer))
        return timer

    def add_reader(self, fd: int, callback: Callback) -> None:
        """Call ``callback()`` whenever ``fd`` is readable (reactor thread only)."""
        self._selector.register(fd, selectors.EVENT_READ, callback)

    def remove_reader(self, fd: int) -> None:
        """Stop watching ``fd`` (no error if it was not watched)."""
        try:
            self._selector.unregister(fd)
        except (KeyError, ValueError):
            pass

    # -------------------------------------------------------------- internals

    def _stop(self, final: Callback | None) -> None:
        try:
            if final is not None:
                final()
        finally:  # a failing final sweep must not leave stop() waiting forever
            self._stopping = True

    def _drain_wake(self) -> None:
        try:
            os.eventfd_read(self._wake_fd)
        except BlockingIOError:
            pass

    def _timeout(self) -> float | None:
        while self._timers and self._timers[0][2].cancelled:
            heapq.heappop(self._timers)
        if self._calls:
            return 0
        if not self._timers:
            return None
        return max(0.0, self._timers[0][0] - time.monotonic())

    def _run(self) -> None:
        while not self._stopping:
            for key, _ in self._selector.select(self._timeout()):
                # an earlier callback of this batch may have unregistered (and closed) it
                if self._selector.get_map().get(key.fd) is key:
                    self._safely(key.data, ())
            self._run_due_timers()
            self._run_calls()
        with self._lock:
            self._closed = True
            self._calls.clear()
            self._selector.close()
            os.close(self._wake_fd)

    def _run_due_timers(self) -> None:
        now = time.monotonic()
        while self._timers and self._timers[0][0] <= now:
            timer = heapq.heappop(self._timers)[2]
            if not timer.cancelled:
                self._safely(timer.callback, timer.args)

    def _run_calls(self) -> None:
        for _ in range(len(self._calls)):
            if self._stopping:
                return
            callback, args = self._calls.popleft()
            self._safely(callback, args)

    @staticmethod
    def _safely(callback: Callback, args: tuple[Any, ...]) -> None:
        try:
            callback(*args)
        except Exception:  # one bad callback must not stop every attempt's I/O
            _log.exception("osmo worker reactor: callback %r failed", callback)
