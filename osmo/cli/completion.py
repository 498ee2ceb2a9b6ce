"""Shell completion for bash, zsh and fish: ``osmo completion SHELL`` prints the script.

Install with one line (docs/reference/cli.md, "Shell completion")::

    eval "$(osmo completion bash)"        # ~/.bashrc (or save it into
                                          # ~/.local/share/bash-completion/completions/osmo)
    eval "$(osmo completion zsh)"         # ~/.zshrc, after compinit
    osmo completion fish | source         # ~/.config/fish/config.fish

Built on ``argcomplete`` (pure Python, small, maintained; pipx and ansible use it), chosen
over ``shtab`` and over scripts of our own: the script a shell loads only hands the command
line back to ``osmo``, which completes it from the very argument parser that parses it (every
verb, option and choice, with nothing generated to drift), in bash, zsh and fish alike; values
only a server knows are plain Python functions. ``shtab`` writes static scripts (no Python at
TAB time) but has no fish, and values from a server would need shell code for each shell. The
cost: each TAB runs ``osmo`` once (about 0.2 s to build the parser).

From a server, where that is cheap: workflow ids (the newest 200 whose name matches what was
typed) and the task names of the workflow on the line. A completion never starts a server
(``autostart`` off) and never hangs: the question gets :data:`TIMEOUT` seconds in a thread the
process abandons, and any failure completes nothing.

The one module that imports ``argcomplete``; ``osmo.cli.main`` calls :func:`complete` only
when a shell asks (``_ARGCOMPLETE`` set), so other commands never import it.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from typing import Any

__all__ = ["SHELLS", "TIMEOUT", "add_parsers", "complete", "run_completion"]

SHELLS = ("bash", "zsh", "fish")
TIMEOUT = 1.5
"""Seconds a completion waits for the server before it offers nothing."""

_MOST_WORKFLOWS = 200
_MOST_TASKS = 1000


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``osmo completion SHELL``."""
    p = sub.add_parser("completion", help="print the shell completion script: "
                       'eval "$(osmo completion bash)" (zsh alike; fish: osmo completion '
                       "fish | source)")
    p.add_argument("shell", choices=SHELLS)


def run_completion(args: argparse.Namespace) -> int:
    """``osmo completion SHELL``: the script that shell loads."""
    from argcomplete.shell_integration import shellcode

    sys.stdout.write(shellcode(["osmo"], shell=args.shell))
    return 0


def complete(parser: argparse.ArgumentParser) -> None:
    """Answer a shell's completion request and exit; return at once if there is none."""
    if "_ARGCOMPLETE" not in os.environ:
        return
    import argcomplete

    for action in _actions(parser):
        if action.dest in ("workflow_id", "workflow_ids"):
            action.completer = _workflow_ids  # type: ignore[attr-defined]
        elif action.dest == "task":
            action.completer = _task_names  # type: ignore[attr-defined]
    argcomplete.autocomplete(parser, always_complete_options=False)


def _actions(parser: argparse.ArgumentParser) -> Iterator[argparse.Action]:
    """Every action of ``parser`` and of its sub-parsers, at any depth."""
    for action in parser._actions:
        yield action
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):  # aliases share a parser
                yield from _actions(sub)


def _asked(parsed_args: argparse.Namespace, question: Callable[[Any], Iterable[str]]
           ) -> list[str]:
    """``question(client)`` of the server on the command line, or [] (none, error, too slow)."""
    answer: list[str] = []

    def ask() -> None:
        from osmo.sdk.client import Client

        try:
            with Client(getattr(parsed_args, "server", None), autostart=False,
                        token=getattr(parsed_args, "token", None)) as client:
                found = list(question(client))
        except Exception:  # noqa: BLE001 - a completion offers nothing rather than fail
            return
        answer.extend(found)

    thread = threading.Thread(target=ask, name="osmo-complete", daemon=True)
    thread.start()
    thread.join(TIMEOUT)
    return [] if thread.is_alive() else answer


def _workflow_ids(prefix: str, parsed_args: argparse.Namespace, **_: Any) -> list[str]:
    """Workflow ids starting with ``prefix``: the newest whose name matches it."""
    name = prefix.rsplit("-", 1)[0] if "-" in prefix else prefix  # ids are NAME-N
    return [i for i in _asked(parsed_args, lambda client: (
        w.id for w in client.list(name=name or None, limit=_MOST_WORKFLOWS)))
            if i.startswith(prefix)]


def _task_names(prefix: str, parsed_args: argparse.Namespace, **_: Any) -> list[str]:
    """Task names of the workflow on the command line that start with ``prefix``."""
    wf_id = getattr(parsed_args, "workflow_id", None)
    if not wf_id:
        return []
    return [t for t in _asked(parsed_args, lambda client: (
        t.name for t in client.get(wf_id, waiting=False, limit=_MOST_TASKS).tasks))
            if t.startswith(prefix)]
