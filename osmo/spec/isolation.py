"""Rendering of spec templates in a child process, under a memory and a time limit.

A template is code its author wrote: five lines of Jinja can ask for gigabytes, or compute a
power of ten that holds the GIL for minutes. So no template is rendered in the calling process
(the server, the CLI or an SDK user's program). Each calling process starts one helper
(:func:`serve_helper`, which imports jinja2 and the spec modules once) on first
use, or early with :func:`warm`. For every rendering the caller hands the helper one end of a
fresh socket pair, and the helper forks a child that owns it:

- the child limits its address space (``RLIMIT_AS``: the helper's size plus
  :data:`MAX_MEMORY`), so an allocation beyond it is a ``MemoryError``, reported as such;
- it arms a real-time timer (:data:`MAX_SECONDS`) whose ``SIGALRM`` has its default action,
  so the kernel ends the child even while a computation holds the GIL;
- it reads the request, renders (``values`` + ``template``), writes the result and exits.

The helper is single-threaded, so forking it is safe, unlike forking a multi-threaded server.
It exits when its caller does (its socket closes). The caller waits on its own socket, never
on the helper, so renderings from several threads run side by side.

A file with no Jinja syntax (no ``{{``, ``{%`` or ``{#`` outside the special tokens) renders
to itself with line endings normalised, exactly as Jinja would; it needs no child. That is
the common case and costs nothing.

This module must not import jinja2: the caller never runs template code.
"""

from __future__ import annotations

import atexit
import gc
import json
import os
import re
import resource
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from osmo.errors import Diagnostic, InfrastructureError
from osmo.spec import tokens

__all__ = ["MAX_MEMORY", "MAX_RENDERED", "MAX_SECONDS", "needs_jinja", "render", "warm"]

MAX_MEMORY = 512 * 2**20  # bytes of address space a rendering may add to the renderer's
MAX_SECONDS = 10.0  # wall time of one rendering, startup of its child included
MAX_RENDERED = 16 * 1024 * 1024  # characters of rendered text
_GRACE = 3.0  # beyond MAX_SECONDS before a caller stops waiting for a child that said nothing
_JINJA = re.compile(r"\{[{%#]")
_HELPER_MAIN = ("import sys; from osmo.spec.isolation import serve_helper; "
                "serve_helper(int(sys.argv[1]))")
_NEWLINE = re.compile(r"\r\n?")


def memory_message() -> str:
    """What a template that ran out of memory is told (the limit named)."""
    return (f"template rendering needed more than {MAX_MEMORY // 2**20} MiB of memory, the "
            "memory limit for templates; make the template produce less")


def time_message(seconds: float) -> str:
    """What a template that ran too long is told (the limit named)."""
    return (f"template rendering took longer than {seconds:g} s, the time limit for "
            "templates; make the template do less work")


def needs_jinja(text: str) -> bool:
    """Whether ``text`` has Jinja syntax outside the special tokens (``{{output}}``...)."""
    return _JINJA.search(tokens.protect(text)[0]) is not None


def _plain(text: str, file: str) -> tuple[str | None, list[Diagnostic]]:
    r"""What Jinja renders from text with no Jinja syntax: the text, line endings as ``\n``."""
    if len(text) > MAX_RENDERED:
        return None, [Diagnostic(file, 0, 0, f"spec exceeds {MAX_RENDERED // 2**20} MiB")]
    protected, saved = tokens.protect(text)
    return tokens.restore(_NEWLINE.sub("\n", protected), saved), []


def render(text: str, file: str, set_values: Sequence[str] = (),
           set_strings: Sequence[str] = ()) -> tuple[str | None, list[Diagnostic]]:
    """Render a spec file's text with its ``default-values`` and the ``--set`` items.

    Returns:
        the rendered text (None on any error) and the diagnostics; a limit that was hit is
        named in its diagnostic.
    """
    if not needs_jinja(text):
        from osmo.spec.values import item_diags

        diags = item_diags(file, set_values, set_strings)
        return (None, diags) if diags else _plain(text, file)
    request = {"text": text, "file": file, "set_values": list(set_values),
               "set_strings": list(set_strings), "seconds": MAX_SECONDS, "memory": MAX_MEMORY}
    return _HELPER.render(request)


def warm() -> None:
    """Start this process's helper now (the server does, so no submit waits for it)."""
    _HELPER.connection()


class _Helper:
    """This process's renderer helper, started on first use and again if it died."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._proc: subprocess.Popen[bytes] | None = None
        self._sock: socket.socket | None = None

    def connection(self) -> socket.socket:
        """The socket to the helper, starting it if it is not running."""
        with self._lock:
            if self._sock is None or self._proc is None or self._proc.poll() is not None:
                self._start()
            assert self._sock is not None
            return self._sock

    def _start(self) -> None:
        self._stop()
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        root = str(Path(__file__).resolve().parents[2])  # this osmo, whatever sys.path says
        path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)
        try:
            with theirs:
                self._proc = subprocess.Popen(
                    [sys.executable, "-c", _HELPER_MAIN, str(theirs.fileno())],
                    pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL,
                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                    start_new_session=True, env={**os.environ, "PYTHONPATH": path})
        except BaseException:
            ours.close()
            raise
        self._sock = ours

    def _stop(self) -> None:
        """Close the socket (the helper then exits) and reap the helper."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self._proc is not None:
            try:
                self._proc.wait(timeout=2)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
            self._proc = None

    def close(self) -> None:
        """Stop the helper (at exit; a later rendering starts another)."""
        with self._lock:
            self._stop()

    def _hand_over(self, conn: socket.socket) -> None:
        """Give the helper one end of a rendering's socket pair (restarting it once).

        Raises:
            InfrastructureError: no helper could be started or reached.
        """
        for attempt in (1, 2):
            try:
                socket.send_fds(self.connection(), [b"r"], [conn.fileno()])
                return
            except OSError as exc:
                if attempt == 2:
                    raise InfrastructureError(f"cannot reach the template renderer process "
                                              f"({exc.strerror or exc})") from None
                with self._lock:
                    if self._proc is not None:
                        self._proc.kill()

    def render(self, request: dict[str, Any]) -> tuple[str | None, list[Diagnostic]]:
        """Send ``request`` to a fresh child and wait for its answer (or its end)."""
        file, seconds = str(request["file"]), float(request["seconds"])
        start = time.monotonic()
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        with ours:
            with theirs:
                self._hand_over(theirs)
            try:
                answer = _exchange(ours, json.dumps(request).encode(), start + seconds + _GRACE)
            except OSError:  # the child died before it read or answered
                answer = None
        if answer is not None:
            try:
                reply = json.loads(answer)
                return reply["text"], [Diagnostic(*d) for d in reply["diags"]]
            except (ValueError, KeyError, TypeError):
                pass  # cut off mid-write: the child was killed while answering
        if time.monotonic() - start >= seconds:
            return None, [Diagnostic(file, 0, 0, time_message(seconds))]
        return None, [Diagnostic(file, 0, 0, "template rendering stopped before it finished "
                                 f"(limits: {MAX_MEMORY // 2**20} MiB of memory, {seconds:g} s); "
                                 "make the template do less")]


def _exchange(conn: socket.socket, request: bytes, deadline: float) -> bytes | None:
    """Send ``request``, then read until EOF; None if ``deadline`` passes first."""
    try:
        conn.settimeout(max(deadline - time.monotonic(), 0.001))
        conn.sendall(request)
        conn.shutdown(socket.SHUT_WR)
        chunks: list[bytes] = []
        while True:
            conn.settimeout(max(deadline - time.monotonic(), 0.001))
            chunk = conn.recv(1 << 20)
            if not chunk:
                return b"".join(chunks)
            chunks.append(chunk)
    except TimeoutError:
        return None


_HELPER = _Helper()
atexit.register(_HELPER.close)


# ---------------------------------------------------------------------- the helper process


def _address_space() -> int:
    """This process's current virtual size in bytes (Linux ``/proc``)."""
    pages = int(Path("/proc/self/statm").read_text().split()[0])
    return pages * os.sysconf("SC_PAGE_SIZE")


def _child(conn: socket.socket) -> None:
    """Render one request read from ``conn`` under its limits; write the answer back."""
    signal.signal(signal.SIGALRM, signal.SIG_DFL)  # the kernel ends us, GIL or not
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    conn.settimeout(None)
    chunks: list[bytes] = []
    while chunk := conn.recv(1 << 20):
        chunks.append(chunk)
    request = json.loads(b"".join(chunks))
    signal.setitimer(signal.ITIMER_REAL, float(request["seconds"]) + 0.5)
    limit = _address_space() + int(request["memory"])
    hard = resource.getrlimit(resource.RLIMIT_AS)[1]
    if hard != resource.RLIM_INFINITY:  # a lower limit set from outside stays
        limit = min(limit, hard)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))  # hard too: no way back up
    from osmo.spec import template, values

    file = str(request["file"])
    try:
        context, diags = values.build_context(request["text"], file, request["set_values"],
                                              request["set_strings"])
        rendered, diags = (None, diags) if diags else template.render(
            request["text"], file, context, seconds=float(request["seconds"]))
    except MemoryError:
        rendered, diags = None, [Diagnostic(file, 0, 0, memory_message())]
    except RecursionError:
        rendered, diags = None, [Diagnostic(file, 0, 0, template.nesting_message())]
    answer = {"text": rendered, "diags": [[d.file, d.line, d.col, d.message] for d in diags]}
    conn.sendall(json.dumps(answer).encode())
    conn.shutdown(socket.SHUT_WR)  # the caller's EOF now, not after this process is torn down


def serve_helper(fd: int) -> None:
    """The helper process: one forked child per socket received on the unix socket ``fd``.

    It runs until the caller is gone. Started by the caller; not for direct use.
    """
    from osmo.spec import template, values  # imported once here, inherited by every child

    # one rendering here fills jinja's lexer and regex caches, which every child inherits
    template.render("{{ x }}", "", values.build_context("default-values: {x: 1}", "")[0])
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)  # children are reaped by the kernel
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the caller decides; we end with it
    gc.freeze()  # a child's collections then skip (and do not copy) the inherited heap
    sock = socket.socket(fileno=fd)
    while True:
        message, fds, _, _ = socket.recv_fds(sock, 16, 1)
        if not message:
            return  # the caller exited
        for fd_ in fds:
            conn = socket.socket(fileno=fd_)
            try:
                pid = os.fork()
            except OSError:
                pid = -1  # the caller sees its socket close and reports it
            if pid == 0:
                code = 0
                try:
                    sock.close()
                    _child(conn)
                except BaseException:  # noqa: BLE001 - nothing may escape a forked child
                    code = 1
                os._exit(code)
            conn.close()
