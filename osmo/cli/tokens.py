"""``osmo token create|list|revoke``: API tokens (admin only).

A token is shown once, by ``create``; the server keeps only its sha256. Give it to a remote
user (``--token``, ``OSMO_TOKEN`` or ``osmo profile set token``) or a worker
(``osmo worker --token`` / ``--token-file``). A worker token names the pools its workers may
serve (``--pool``, repeatable; ``--pool '*'``: every pool).
"""

from __future__ import annotations

import argparse
import time

from osmo.cli.render import console, print_json, safe

__all__ = ["add_parsers", "run_token"]


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``token``."""
    p = sub.add_parser("token", help="API tokens: create, list, revoke (admin)")
    verbs = p.add_subparsers(dest="token_verb", metavar="VERB", required=True)
    c = verbs.add_parser("create", help="a new token, printed once")
    c.add_argument("name")
    c.add_argument("--role", choices=("user", "worker", "admin"), default="user",
                   help="user: submit and read, control own workflows; worker: run tasks; "
                        "admin: everything (default: user)")
    c.add_argument("--pool", action="append", dest="pools", metavar="POOL", default=[],
                   help="a pool the worker token may serve (repeatable; required for "
                        "--role worker; '*': every pool)")
    c.add_argument("--format", choices=("text", "json"), default="text")
    ls = verbs.add_parser("list", help="every token's name, role, pools and state")
    ls.add_argument("--format", choices=("text", "json"), default="text")
    r = verbs.add_parser("revoke", help="refuse a token from now on")
    r.add_argument("name")


def run_token(args: argparse.Namespace) -> int:
    """``osmo token create|list|revoke``."""
    from osmo.sdk.client import Client

    with Client(args.server) as client:
        if args.token_verb == "create":
            token = client.create_token(args.name, args.role, pools=args.pools)
            if args.format == "json":
                print_json({"name": args.name, "role": args.role, "pools": args.pools or None,
                            "token": token})
            else:
                print(token)
        elif args.token_verb == "list":
            rows = client.tokens()
            if args.format == "json":
                print_json(rows)
            for row in rows if args.format == "text" else ():
                revoked = row["revoked_at"]
                state = (time.strftime("revoked %Y/%m/%d %H:%M", time.localtime(revoked))
                         if revoked else "live")
                pools = row.get("pools")
                bound = f"pools {', '.join(safe(p) for p in pools)}  " if pools else ""
                console.print(f"{safe(row['name'])}  {row['role']}  {bound}{state}",
                              markup=False)
        else:
            client.revoke_token(args.name)
            console.print(f"revoked token {safe(args.name)}", markup=False)
    return 0
