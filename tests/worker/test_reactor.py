"""The pool's event loop: ordered calls, timers, readers, failing callbacks."""

from __future__ import annotations

import os
import queue
import threading

from osmo.worker.reactor import Reactor

TIMEOUT = 30.0


def test_calls_run_in_order_on_the_reactor_thread() -> None:
    reactor = Reactor("test")
    seen: queue.Queue[tuple[int, str]] = queue.Queue()
    for i in range(100):
        reactor.call_soon(lambda i=i: seen.put((i, threading.current_thread().name)))
    got = [seen.get(timeout=TIMEOUT) for _ in range(100)]
    reactor.stop()
    assert [i for i, _ in got] == list(range(100))
    assert {name for _, name in got} == {"test"}


def test_timers_fire_in_deadline_order_and_cancel() -> None:
    reactor = Reactor("test")
    seen: queue.Queue[str] = queue.Queue()

    def schedule() -> None:
        reactor.call_later(0.05, seen.put, "late")
        reactor.call_later(0.0, seen.put, "early")
        reactor.call_later(0.01, seen.put, "cancelled").cancel()

    reactor.call_soon(schedule)
    assert [seen.get(timeout=TIMEOUT), seen.get(timeout=TIMEOUT)] == ["early", "late"]
    reactor.stop()
    assert seen.empty()


def test_readers_and_failing_callbacks() -> None:
    reactor = Reactor("test")
    seen: queue.Queue[bytes] = queue.Queue()
    read_fd, write_fd = os.pipe()

    def on_read() -> None:
        seen.put(os.read(read_fd, 100))

    reactor.call_soon(lambda: 1 / 0)  # logged, the loop goes on
    reactor.call_soon(reactor.add_reader, read_fd, on_read)
    os.write(write_fd, b"hello")
    assert seen.get(timeout=TIMEOUT) == b"hello"
    reactor.call_soon(reactor.remove_reader, read_fd)
    reactor.stop(lambda: seen.put(b"final"))
    assert seen.get(timeout=TIMEOUT) == b"final"
    reactor.call_soon(seen.put, b"after stop")  # ignored
    reactor.stop()
    os.close(read_fd)
    os.close(write_fd)
    assert seen.empty()


def test_stop_returns_even_if_the_final_sweep_fails() -> None:
    reactor = Reactor("test")

    def broken() -> None:
        raise RuntimeError("sweep failed")

    done = threading.Event()
    threading.Thread(target=lambda: (reactor.stop(broken), done.set()), daemon=True).start()
    assert done.wait(timeout=TIMEOUT), "stop() must not wait forever when the final call raises"
