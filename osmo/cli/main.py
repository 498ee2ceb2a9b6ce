"""The ``osmo`` command line: argument parsing and exit codes.

Exit codes (documented in docs/reference/exit-codes.md): 0 ok; 1 workflow failed; 2 invalid
input or usage; 3 server unreachable or infrastructure error; 130 interrupted. A user mistake
never prints a traceback. Verbs exist both at the top level (``osmo submit``) and under
``osmo workflow`` for OSMO parity.

Arguments are taken as OSMO's CLI takes them: ``--set``, ``--set-string`` and ``--set-env``
each take one or more ``K=V`` and may be repeated (later values win); the global options
``--server`` and ``--format``/``-t`` are accepted before or after the verb (after it, a
verb's own ``-t`` keeps its meaning: ``osmo logs -t`` is the task).
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
from collections.abc import Iterator, Sequence

from osmo.cli.artifacts import add_parsers as add_artifact_parsers
from osmo.cli.completion import add_parsers as add_completion_parsers
from osmo.cli.datasets import add_credential_parsers
from osmo.cli.datasets import add_parsers as add_dataset_parsers
from osmo.cli.interactive import add_parsers as add_interactive_parsers
from osmo.cli.plugins import add_parsers as add_plugin_parsers
from osmo.cli.pools import add_parsers as add_pool_parsers
from osmo.cli.remote import add_parsers as add_remote_parsers
from osmo.cli.render import QUERY_LIMIT
from osmo.cli.robotics import add_parsers as add_robotics_parsers
from osmo.cli.tokens import add_parsers as add_token_parsers
from osmo.errors import OsmoError, UsageError
from osmo.options import ServerOptions

__all__ = ["build_parser", "main"]

_WORKFLOW_VERBS = ("submit", "validate", "query", "status", "list", "logs", "events", "tag",
                   "cancel", "restart", "spec", "exec", "port-forward")


def _add_format(p: argparse.ArgumentParser) -> None:
    p.add_argument("--format", "-t", "--format-type", dest="format", choices=("text", "json"),
                   default="text", help="output format")


_TEMPLATE_FLAGS = (("--set", "set_values"), ("--set-string", "set_strings"),
                   ("--set-env", "set_env"))


def _add_template_args(p: argparse.ArgumentParser) -> None:
    # nargs="?": a spec file swallowed by a --set gets its own error (see _check_spec_file)
    p.add_argument("file", nargs="?", help="workflow spec (YAML)")
    helps = ("template variables (cast to int, then float, else string)",
             "template variables kept as strings", "environment variables added to every task")
    for (flag, dest), text in zip(_TEMPLATE_FLAGS, helps, strict=True):
        p.add_argument(flag, dest=dest, nargs="+", action="extend", default=[], metavar="K=V",
                       help=f"{text}; one or more, repeatable, later values win")
    p.add_argument("--allow-localpath", action="append", default=[], metavar="DIR",
                   help="let 'files: localpath:' also read DIR's tree (repeatable; default: "
                        "only the spec's folder tree; never osmo's home)")


def _check_spec_file(args: argparse.Namespace) -> None:
    """A verb with a spec file has one: else say whether a ``--set`` took it, and the fix."""
    if not hasattr(args, "set_values") or args.file is not None:
        return
    verb = getattr(args, "wf_verb", None) or args.verb
    for flag, dest in _TEMPLATE_FLAGS:
        values = getattr(args, dest)
        taken = [v for v in values if "=" not in v]
        if len(taken) == 1:
            rest = " ".join(v for v in values if v != taken[0])
            raise UsageError(f"no workflow spec file: {flag} takes every K=V after it, and it "
                             f"took {taken[0]!r}. Put the file first: osmo {verb} {taken[0]} "
                             f"{flag} {rest}")
        if taken:
            raise UsageError(f"no workflow spec file, and {flag} got values that are not "
                             f"K=V: {' '.join(taken)}")
    raise UsageError(f"no workflow spec file: give its path, e.g. osmo {verb} workflow.yaml")


def _add_workflow_verbs(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("submit", help="submit a workflow")
    _add_template_args(p)
    p.add_argument("--pool", "-p", help="target pool (overrides workflow.pool)")
    p.add_argument("--label", dest="labels", action="append", default=[], metavar="K=V",
                   help="a workflow label, merged over workflow.labels (repeatable)")
    p.add_argument("--priority", type=str.upper, choices=("HIGH", "NORMAL", "LOW"),
                   default="NORMAL", help="placement order when resources are short, with "
                   "ageing: nothing waits forever (default NORMAL)")
    p.add_argument("--wait", action="store_true", help="show progress; exit 0 only if COMPLETED")
    p.add_argument("--dry-run", action="store_true", help="print the rendered spec; submit nothing")
    p.add_argument("--runtime", choices=("kubernetes",),
                   help="with --dry-run: print instead the Kubernetes objects (a v1 List: "
                        "pods, Secrets, group Services, PodGroups) the image tasks' first "
                        "attempts would create")
    p.add_argument("--kubernetes-config", metavar="FILE",
                   help="with --runtime kubernetes: the pool's configuration (as the "
                        "worker's --kubernetes-config)")
    p.add_argument("--task", help="with --runtime kubernetes: only this task's objects")
    reuse = p.add_mutually_exclusive_group()
    reuse.add_argument("--no-cache", action="store_true",
                       help="run every task even if an identical earlier run could be reused")
    reuse.add_argument("--reuse", action="store_true",
                       help="let every task whose spec does not say (cache:) reuse an identical "
                            "earlier success; by default only typed tasks and tasks whose "
                            "output another task takes do")
    _add_format(p)

    p = sub.add_parser("validate", help="check a spec without submitting it")
    _add_template_args(p)

    for name in ("query", "status"):
        p = sub.add_parser(name, help="a workflow's status and task table")
        p.add_argument("workflow_id")
        p.add_argument("-v", "--verbose", action="store_true")
        p.add_argument("-s", "--status", action="append", default=[],
                       help="only tasks with this status (repeatable)")
        p.add_argument("-n", "--limit", type=int, default=None,
                       help=f"show at most this many tasks (default {QUERY_LIMIT:,} in the "
                            "table, all with --format json; 0: none, only the counts)")
        _add_format(p)

    p = sub.add_parser("list", help="list workflows")
    p.add_argument("-s", "--status", action="append", default=[], help="filter by status")
    p.add_argument("--name", help="filter by name (substring)")
    p.add_argument("-c", "--count", type=int, default=20, help="how many (default 20)")
    p.add_argument("--label", dest="labels", action="append", default=[], metavar="K=V",
                   help="only workflows with this label (repeatable: all of them)")
    _add_format(p)

    p = sub.add_parser("logs", help="a workflow's logs")
    p.add_argument("workflow_id")
    p.add_argument("-t", "--task")
    p.add_argument("-r", "--retry", type=int)
    p.add_argument("-n", "--tail", "--lines", dest="lines", type=int, metavar="N",
                   help="only the last N lines")
    p.add_argument("--since", metavar="WHEN",
                   help="only lines written since WHEN: a duration ago (30s, 10m, 2h, 1d) or "
                        "an ISO time (2024-05-01T10:00, local time unless it names a zone)")
    p.add_argument("-f", "--follow", action="store_true",
                   help="follow until the workflow ends (with --tail/--since: from there)")
    p.add_argument("--error", action="store_true", help="stderr lines only")

    p = sub.add_parser("events", help="a workflow's scheduling timeline (queued, placed, "
                       "started, retried, why it failed)")
    p.add_argument("workflow_id")
    p.add_argument("-t", "--task", help="only this task's events")
    p.add_argument("--format", dest="format", choices=("text", "json"), default="text",
                   help="output format (-t is the task here, as in logs)")

    p = sub.add_parser("tag", help="add or remove a workflow's tags")
    p.add_argument("workflow_id")
    p.add_argument("--add", nargs="+", action="extend", default=[], metavar="TAG")
    p.add_argument("--remove", nargs="+", action="extend", default=[], metavar="TAG")
    _add_format(p)

    p = sub.add_parser("cancel", help="cancel workflows")
    p.add_argument("workflow_ids", nargs="+", metavar="workflow_id")

    p = sub.add_parser("restart", help="rerun what did not complete, reusing completed outputs")
    p.add_argument("workflow_id")
    p.add_argument("--wait", action="store_true")

    p = sub.add_parser("spec", help="print the spec a workflow was submitted with")
    p.add_argument("workflow_id")
    add_interactive_parsers(sub)


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser."""
    parser = argparse.ArgumentParser(prog="osmo", description=(
        "Run OSMO-spec workflows on this machine or a fleet. Exit codes: 0 ok, 1 workflow "
        "failed, 2 invalid input or usage, 3 server unreachable or infrastructure error."))
    parser.add_argument("--server", help="server endpoint, e.g. tcp/127.0.0.1:7447 "
                        "(default: OSMO_SERVER, else the local server, started if needed)")
    parser.add_argument("--token", help="API token for a remote server (default: OSMO_TOKEN, "
                        "the profile's token, or this home's admin token for its own server)")
    parser.add_argument("--format", "-t", "--format-type", dest="global_format",
                        metavar="FORMAT", help="output format of the verb (text, json, ...)")
    parser.add_argument("--version", action=_Version, nargs=0,
                        help="print the installed osmo's version and exit")
    sub = parser.add_subparsers(dest="verb", metavar="COMMAND")
    _add_workflow_verbs(sub)
    wf = sub.add_parser("workflow", help="the same verbs, OSMO style: osmo workflow submit ...")
    _add_workflow_verbs(wf.add_subparsers(dest="wf_verb", metavar="VERB", required=True))

    add_artifact_parsers(sub)
    add_dataset_parsers(sub)
    add_credential_parsers(sub)
    add_pool_parsers(sub)
    add_plugin_parsers(sub)
    add_robotics_parsers(sub)
    add_token_parsers(sub)

    p = sub.add_parser("server", help="run the server in the foreground, or start|stop|status")
    p.add_argument("action", nargs="?", choices=("start", "stop", "status", "run"), default="run")
    ServerOptions.add_arguments(p)
    _add_format(p)
    add_remote_parsers(sub)
    add_completion_parsers(sub)
    for verb in _verb_parsers(parser):
        _accept_global_options(verb)
    return parser


class _Version(argparse.Action):
    """``--version``: the installed package's version, from its metadata.

    Read only when asked (the metadata lookup costs ~50 ms, too much for every command). From
    a source tree that is not installed, the source's version, said so.
    """

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: object, option_string: str | None = None) -> None:
        from importlib.metadata import PackageNotFoundError, version

        try:
            text = version("osmo")
        except PackageNotFoundError:
            from osmo.version import __version__

            text = f"{__version__} (source tree, not installed)"
        sys.stdout.write(f"osmo {text}\n")
        parser.exit(0)


def _verb_parsers(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    """Every sub-parser, at any depth (``osmo workflow submit``, ``osmo dataset info``)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):  # aliases share a parser
                yield sub
                yield from _verb_parsers(sub)


def _accept_global_options(p: argparse.ArgumentParser) -> None:
    """Let ``--server``, ``--token`` and ``--format`` follow the verb, not overriding one before.

    A verb's ``--format`` default becomes None (so it cannot hide a global ``--format``) and
    is kept as ``_format_default``; :func:`_resolve_format` puts the answer back.
    """
    options = {o for a in p._actions for o in a.option_strings}
    if "--server" not in options:
        p.add_argument("--server", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    if "--token" not in options:  # ``osmo worker`` has its own
        p.add_argument("--token", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    for action in p._actions:
        if action.dest == "format":
            p.set_defaults(_format_default=action.default, _format_choices=action.choices)
            action.default = None
    if "--format" not in options:
        p.add_argument("--format", dest="global_format", default=argparse.SUPPRESS,
                       help=argparse.SUPPRESS)


def _resolve_format(args: argparse.Namespace) -> None:
    """The verb's format: its own option, else the global one, else its default."""
    chosen = getattr(args, "global_format", None)
    if getattr(args, "format", None) is None and hasattr(args, "_format_default"):
        choices = args._format_choices
        if chosen is not None and choices and chosen not in choices:
            raise UsageError(f"--format {chosen!r} is not one of {', '.join(choices)} here")
        args.format = chosen if chosen is not None else args._format_default


def _parse(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.Namespace:
    """Parse ``argv``; for ``exec``, everything after the first ``--`` is the command.

    (argparse would read a ``--group`` after the task as part of a trailing command.)
    """
    if "--" in argv:
        cut = argv.index("--")
        head = parser.parse_known_args(argv[:cut])[0] if argv[:cut] else None
        if head is not None and (getattr(head, "wf_verb", None) or head.verb) == "exec":
            args = parser.parse_args(argv[:cut])
            args.command = argv[cut + 1:]
            return args
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns (and, as a console script, exits with) the exit code."""
    from osmo.cli import commands
    from osmo.cli.render import print_error

    parser = build_parser()
    if "_ARGCOMPLETE" in os.environ:  # a shell asks for completions (osmo.cli.completion)
        from osmo.cli.completion import complete

        complete(parser)
    try:
        args = _parse(parser, list(sys.argv[1:] if argv is None else argv))
    except SystemExit as exc:  # argparse exits 2 on usage errors, 0 on --help
        return int(exc.code or 0)
    verb = getattr(args, "wf_verb", None) or args.verb
    if getattr(args, "token", None) and verb != "worker":
        os.environ["OSMO_TOKEN"] = args.token  # every Client this command opens sends it
    if verb is None:
        parser.print_help()
        return 2
    try:
        _resolve_format(args)
        _check_spec_file(args)
        return commands.run(verb, args)
    except OsmoError as exc:
        print_error(str(exc) or type(exc).__name__)
        return exc.exit_code
    except KeyboardInterrupt:
        return 130


def entry() -> None:
    """Console-script entry point.

    A CLI process is short-lived: it collects garbage every 50,000 allocations instead of
    700, which makes checking a 100,000-task spec several times faster (see the server's
    ``_tune_interpreter``).
    """
    gc.set_threshold(50_000, 20, 50)
    sys.exit(main())


if __name__ == "__main__":
    entry()
