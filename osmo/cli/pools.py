"""CLI verbs for capacity: ``osmo pool list`` and ``osmo resource list`` (alias ``workers``)."""

from __future__ import annotations

import argparse
from typing import Any

from osmo.cli.render import console, print_json, resource_table
from osmo.sdk.client import Client

__all__ = ["add_parsers", "run_pool", "run_resource"]


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Register ``pool``, ``resource`` and ``workers``."""
    p = sub.add_parser("pool", help="pools and their total capacity")
    verbs = p.add_subparsers(dest="pool_verb", metavar="VERB", required=True)
    q = verbs.add_parser("list", help="each pool: nodes, platforms, cpu/gpu/memory used/total")
    q.add_argument("--format", "-t", dest="format", choices=("text", "json"), default="text")
    for name in ("resource", "workers"):
        p = sub.add_parser(name, help="nodes (workers) with their capacity used/total")
        if name == "resource":
            verbs = p.add_subparsers(dest="resource_verb", metavar="VERB", required=True)
            p = verbs.add_parser("list", help="every node with cpu/gpu/memory used/total")
        p.add_argument("--format", "-t", dest="format", choices=("text", "json"),
                       default="text")


def _nodes(args: argparse.Namespace) -> list[dict[str, Any]]:
    with Client(args.server) as client:
        return client.pools()


def run_resource(args: argparse.Namespace) -> int:
    """``osmo resource list`` / ``osmo workers``."""
    nodes = _nodes(args)
    if args.format == "json":
        print_json(nodes)
    else:
        console.print(resource_table(nodes, by="node"))
    return 0


def _sandbox(kinds: list[str]) -> str:
    """A pool's sandbox: its nodes' one kind, or how many lack one (``none`` on 2 of 5)."""
    if len(set(kinds)) == 1:
        return kinds[0]
    return f"none on {kinds.count('none')} of {len(kinds)}"


def run_pool(args: argparse.Namespace) -> int:
    """``osmo pool list``: nodes summed per pool, with their sandbox (``bwrap`` or ``none``)."""
    pools: dict[str, dict[str, Any]] = {}
    for node in _nodes(args):
        pool = pools.setdefault(node["pool"], {"pool": node["pool"], "nodes": 0,
                                               "platforms": set(), "runtimes": set(),
                                               "used": {}, "total": {}, "sandboxes": []})
        pool["nodes"] += 1
        pool["platforms"].update(node.get("platforms") or [node["platform"] or "-"])
        pool["runtimes"].add(node.get("runtime") or "-")
        pool["sandboxes"].append(node.get("sandbox", "none"))
        for side in ("used", "total"):
            for key, value in node[side].items():
                pool[side][key] = pool[side].get(key, 0) + value
    for pool in pools.values():
        pool["sandbox"] = _sandbox(pool.pop("sandboxes"))
    rows = [{**p, "platforms": sorted(p["platforms"]), "runtimes": sorted(p["runtimes"])}
            for p in pools.values()]
    if args.format == "json":
        print_json(rows)
    else:
        console.print(resource_table(rows, by="pool"))
    return 0
