"""``osmo server [start|stop|status]``: the local server's life, and the options it keeps.

An explicit start (``osmo server start`` or the foreground ``osmo server``) saves its options
in the home (``osmo.options.remember``), and says what changed from the saved ones:
the new ones win, and the next automatic start uses them. A start while a server runs changes
nothing, and says so when its options differ from the running server's.
"""

from __future__ import annotations

import argparse
import shlex

from osmo import options as opts
from osmo.cli.render import console, err_console, print_json
from osmo.config import open_home
from osmo.options import ServerOptions
from osmo.sdk.connect import running_options, server_status, start_server, stop_server

__all__ = ["run_server"]


def run_server(args: argparse.Namespace) -> int:
    """Run ``osmo server`` with ``args.action`` (run, start, stop, status)."""
    options = ServerOptions.from_args(args)
    if args.action == "run":
        from osmo.server.app import serve

        home = open_home()
        _say_changes(opts.remember(home, options))
        console.print("osmo server running in the foreground (Ctrl-C to stop)", markup=False)
        serve(home, options)
        return 0
    if args.action == "start":
        return _start(options)
    if args.action == "stop":
        pid = stop_server()
        console.print(f"stopped osmo server (pid {pid})" if pid else "no osmo server running",
                      markup=False)
        return 0
    return _status(args.format)


def _start(options: ServerOptions) -> int:
    status = server_status()
    if status is not None:
        running = _parsed(running_options())
        changes = opts.option_changes(running, opts.absolute(options)) if running else []
        console.print(f"osmo server already running: pid {status.pid}, {status.endpoint}",
                      markup=False)
        if changes:
            console.print("it runs with other options; to use the new ones, `osmo server "
                          "stop` and start again:\n  " + "\n  ".join(changes), markup=False)
        return 0
    _say_changes(opts.remember(open_home(), options))
    info = start_server(options=options)
    console.print(f"osmo server running: pid {info.pid}, {info.endpoint}", markup=False)
    for warning in info.warnings:  # e.g. no sandbox: said where the user looks, not only in the log
        err_console.print(warning, markup=False)
    return 0


def _say_changes(changes: list[str]) -> None:
    if changes:
        console.print("server options changed since the last start (the new ones are saved "
                      "and used by automatic starts):\n  " + "\n  ".join(changes),
                      markup=False)


def _status(fmt: str) -> int:
    status = server_status()
    home = open_home()
    options = running_options() if status else None
    if fmt == "json":
        print_json({**status.__dict__, "options": options} if status else None)
        return 0 if status else 3
    if status:
        console.print(f"running: pid {status.pid}, {status.endpoint}", markup=False)
        if options is not None:
            console.print(f"options: {shlex.join(options) or '(defaults)'}", markup=False)
    else:
        console.print("not running", markup=False)
        saved = opts.saved_options(home)
        if saved is not None:
            console.print(f"an automatic start uses: {shlex.join(saved.to_argv()) or '(defaults)'}"
                          f" (saved in {home.server_options})", markup=False)
    return 0 if status else 3


def _parsed(argv: list[str] | None) -> ServerOptions | None:
    """The options a running server reported as flags (None: unknown or unreadable)."""
    try:
        return opts.options_from_argv(argv) if argv is not None else None
    except ValueError:
        return None
