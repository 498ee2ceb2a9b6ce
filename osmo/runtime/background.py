"""A runtime's own background calls: each on a thread of its own, waited for at close.

What a runtime must not do on the pool's reactor (a container's removal, a pod group's
deletion) it hands to :class:`Background`; the runtime's ``close`` waits for them.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

__all__ = ["Background"]


class Background:
    """Calls under way on their own threads (thread-safe).

    Args:
        name: the threads' name.
    """

    def __init__(self, name: str) -> None:
        self._name = name
        self._threads: set[threading.Thread] = set()
        self._lock = threading.Lock()

    def later(self, fn: Callable[..., object], *args: object) -> None:
        """Call ``fn(*args)`` on a thread of its own; :meth:`close` waits for it."""
        def run() -> None:
            try:
                fn(*args)
            finally:
                with self._lock:
                    self._threads.discard(thread)

        thread = threading.Thread(target=run, name=self._name, daemon=True)
        with self._lock:
            self._threads.add(thread)
        thread.start()

    def close(self) -> None:
        """Wait for the calls still under way (and those they start)."""
        while True:
            with self._lock:
                threads = list(self._threads)
            if not threads:
                return
            for thread in threads:
                thread.join()
