"""CLI verbs for data: ``osmo dataset ...`` and ``osmo credential ...``.

``osmo dataset list|info|tag|download|upload``, and ``osmo credential set|list|delete`` (the secrets
data URLs and tasks use).
"""

from __future__ import annotations

import argparse

from osmo.cli.render import console, print_json, safe, transfer_progress
from osmo.errors import UsageError
from osmo.sdk.client import Client

__all__ = ["add_credential_parsers", "add_parsers", "run_credential", "run_dataset"]


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``dataset`` on the top-level parser."""
    p = sub.add_parser("dataset", help="versioned datasets: list, info, tag, download, upload")
    verbs = p.add_subparsers(dest="dataset_verb", metavar="VERB", required=True)
    q = verbs.add_parser("list", help="datasets and their versions")
    q.add_argument("name", nargs="?")
    q.add_argument("--format", "-t", dest="format", choices=("text", "json"), default="text")
    q = verbs.add_parser("info", help="one version: files, tags, what made it")
    q.add_argument("ref", help="NAME[:TAG_OR_VERSION] (default: newest)")
    q.add_argument("--format", "-t", dest="format", choices=("text", "json"), default="text")
    q = verbs.add_parser("tag", help="point a tag at a version")
    q.add_argument("ref")
    q.add_argument("tag")
    q = verbs.add_parser("download", help="write a version's files (verified) to a folder")
    q.add_argument("ref")
    q.add_argument("-o", "--output", required=True)
    q.add_argument("--regex", help="only files whose path matches")
    q = verbs.add_parser("upload", help="make a new version from a local folder")
    q.add_argument("name")
    q.add_argument("path")
    q.add_argument("--metadata", action="append", default=[], metavar="K=V")


def run_dataset(args: argparse.Namespace) -> int:
    """Run one ``osmo dataset`` verb."""
    with Client(args.server) as client:
        verb = args.dataset_verb
        if verb == "list":
            rows = client.datasets(args.name)
            if args.format == "json":
                print_json(rows)
            for r in rows if args.format == "text" else ():
                tags = f" [{', '.join(r['tags'])}]" if r["tags"] else ""
                console.print(safe(f"{r['name']}:{r['version']}{tags}  {r['files']} files  "
                                   f"{r['size']} B  {r['created']}  by "
                                   f"{r['made_by'] or 'upload'}"), markup=False)
        elif verb == "info":
            info = client.dataset(args.ref)
            if args.format == "json":
                print_json(info)
            else:
                console.print(safe(f"{info['name']}:{info['version']}  {info['manifest']}  "
                                   f"made by {info['made_by'] or 'upload'}"), markup=False)
                for f in info["files"]:
                    console.print(f"  {safe(f['path'])}  {f['size']} B  {f['digest']}",
                                  markup=False)
        elif verb == "tag":
            r = client.tag_dataset(args.ref, args.tag)
            console.print(f"{r['name']}:{r['tag']} -> version {r['version']}", markup=False)
        elif verb == "download":
            with transfer_progress(f"download {args.ref}") as progress:
                written = client.download_dataset(args.ref, args.output, regex=args.regex,
                                                  on_progress=progress)
            for path in written:
                console.print(safe(path), markup=False)
        else:
            metadata = dict(_pair(m) for m in args.metadata)
            with transfer_progress(f"upload {args.name}") as progress:
                version = client.upload_dataset(args.name, args.path, metadata=metadata,
                                                on_progress=progress)
            console.print(f"{args.name}:{version}", markup=False)
    return 0


def _pair(item: str) -> tuple[str, str]:
    key, sep, value = item.partition("=")
    if not sep or not key:
        raise UsageError(f"--metadata expects K=V, got '{item}'")
    return key, value


def add_credential_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``credential`` on the top-level parser."""
    p = sub.add_parser("credential", help="named secrets on the server (for data URLs and tasks)")
    verbs = p.add_subparsers(dest="credential_verb", metavar="VERB", required=True)
    q = verbs.add_parser("set", help="store a credential")
    q.add_argument("name", help="e.g. s3, s3://BUCKET for one bucket, or a name tasks use")
    q.add_argument("--payload", action="append", default=[], metavar="K=V", required=True)
    verbs.add_parser("list", help="names and keys (never values)")
    q = verbs.add_parser("delete", help="remove a credential")
    q.add_argument("name")


def run_credential(args: argparse.Namespace) -> int:
    """Run one ``osmo credential`` verb."""
    with Client(args.server) as client:
        if args.credential_verb == "set":
            client.set_credential(args.name, dict(_pair(p) for p in args.payload))
            console.print(f"stored credential '{args.name}'", markup=False)
        elif args.credential_verb == "list":
            for c in client.credentials():
                console.print(f"{c['name']}  keys: {', '.join(c['keys'])}", markup=False)
        else:
            client.delete_credential(args.name)
            console.print(f"deleted credential '{args.name}'", markup=False)
    return 0
