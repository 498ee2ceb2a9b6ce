"""The ``osmo`` command line: argument parsing and exit codes.

Exit codes (documented in the README): 0 ok; 1 workflow failed; 2 invalid input or usage;
3 server unreachable or infrastructure error; 130 interrupted. A user mistake never prints a
traceback. Verbs exist both at the top level (``osmo submit``) and under ``osmo workflow``
for OSMO parity.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from osmo.cli.artifacts import add_parsers as add_artifact_parsers
from osmo.cli.datasets import add_credential_parsers
from osmo.cli.datasets import add_parsers as add_dataset_parsers
from osmo.cli.plugins import add_parsers as add_plugin_parsers
from osmo.cli.pools import add_parsers as add_pool_parsers
from osmo.cli.remote import add_parsers as add_remote_parsers
from osmo.cli.robotics import add_parsers as add_robotics_parsers
from osmo.cli.tokens import add_parsers as add_token_parsers
from osmo.errors import OsmoError
from osmo.server.options import ServerOptions

__all__ = ["build_parser", "main"]

_WORKFLOW_VERBS = ("submit", "validate", "query", "status", "list", "logs", "cancel", "restart",
                   "spec")


def _add_format(p: argparse.ArgumentParser) -> None:
    p.add_argument("--format", "-t", "--format-type", dest="format", choices=("text", "json"),
                   default="text", help="output format")


def _add_template_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", help="workflow spec (YAML)")
    p.add_argument("--set", dest="set_values", action="append", default=[], metavar="K=V",
                   help="template variable (cast to int, then float, else string)")
    p.add_argument("--set-string", dest="set_strings", action="append", default=[],
                   metavar="K=V", help="template variable kept as a string")
    p.add_argument("--set-env", dest="set_env", action="append", default=[], metavar="K=V",
                   help="environment variable added to every task")


def _add_workflow_verbs(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("submit", help="submit a workflow")
    _add_template_args(p)
    p.add_argument("--pool", help="target pool (overrides workflow.pool)")
    p.add_argument("--wait", action="store_true", help="show progress; exit 0 only if COMPLETED")
    p.add_argument("--dry-run", action="store_true", help="print the rendered spec; submit nothing")
    p.add_argument("--no-cache", action="store_true",
                   help="run every task even if an identical earlier run could be reused")
    _add_format(p)

    p = sub.add_parser("validate", help="check a spec without submitting it")
    _add_template_args(p)

    for name in ("query", "status"):
        p = sub.add_parser(name, help="a workflow's status and task table")
        p.add_argument("workflow_id")
        p.add_argument("-v", "--verbose", action="store_true")
        _add_format(p)

    p = sub.add_parser("list", help="list workflows")
    p.add_argument("-s", "--status", action="append", default=[], help="filter by status")
    p.add_argument("--name", help="filter by name (substring)")
    p.add_argument("-c", "--count", type=int, default=20, help="how many (default 20)")
    _add_format(p)

    p = sub.add_parser("logs", help="a workflow's logs")
    p.add_argument("workflow_id")
    p.add_argument("-t", "--task")
    p.add_argument("-r", "--retry", type=int)
    p.add_argument("-n", "--lines", type=int, help="last N lines")
    p.add_argument("-f", "--follow", action="store_true", help="follow until the workflow ends")

    p = sub.add_parser("cancel", help="cancel a workflow")
    p.add_argument("workflow_id")

    p = sub.add_parser("restart", help="rerun what did not complete, reusing completed outputs")
    p.add_argument("workflow_id")
    p.add_argument("--wait", action="store_true")

    p = sub.add_parser("spec", help="print the spec a workflow was submitted with")
    p.add_argument("workflow_id")


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser."""
    parser = argparse.ArgumentParser(prog="osmo", description=(
        "Run OSMO-spec workflows on this machine or a fleet. Exit codes: 0 ok, 1 workflow "
        "failed, 2 invalid input or usage, 3 server unreachable or infrastructure error."))
    parser.add_argument("--server", help="server endpoint, e.g. tcp/127.0.0.1:7447 "
                        "(default: OSMO_SERVER, else the local server, started if needed)")
    parser.add_argument("--token", help="API token for a remote server (default: OSMO_TOKEN, "
                        "the profile's token, or this home's admin token for its own server)")
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
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns (and, as a console script, exits with) the exit code."""
    from osmo.cli import commands
    from osmo.cli.render import print_error

    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse exits 2 on usage errors, 0 on --help
        return int(exc.code or 0)
    verb = getattr(args, "wf_verb", None) or args.verb
    if getattr(args, "token", None) and verb != "worker":
        import os

        os.environ["OSMO_TOKEN"] = args.token  # every Client this command opens sends it
    if verb is None:
        parser.print_help()
        return 2
    try:
        return commands.run(verb, args)
    except OsmoError as exc:
        print_error(str(exc) or type(exc).__name__)
        return exc.exit_code
    except KeyboardInterrupt:
        return 130


def entry() -> None:
    """Console-script entry point."""
    sys.exit(main())


if __name__ == "__main__":
    entry()
