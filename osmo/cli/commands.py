"""The CLI verbs: each turns parsed arguments into SDK calls and prints the result."""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from osmo.cli.artifacts import run_artifacts, run_lineage
from osmo.cli.completion import run_completion
from osmo.cli.datasets import run_credential, run_dataset
from osmo.cli.interactive import run_exec, run_forward
from osmo.cli.plugins import run_plugins
from osmo.cli.pools import run_pool, run_resource
from osmo.cli.remote import run_health, run_profile, run_worker
from osmo.cli.render import (
    QUERY_LIMIT,
    console,
    events_text,
    format_log,
    info_dict,
    live_progress,
    not_shown_line,
    print_error,
    print_json,
    reuse_notice,
    safe,
    task_table,
    workflow_header,
    workflows_table,
)
from osmo.cli.robotics import run_eval, run_view
from osmo.cli.server import run_server
from osmo.cli.tokens import run_token
from osmo.errors import OsmoError, UsageError, WorkflowFailed
from osmo.names import check_label
from osmo.sdk.client import Client, WorkflowInfo

__all__ = ["run"]


def _client(args: argparse.Namespace) -> Client:
    return Client(args.server)


def _types(file: str) -> Any:
    """Task types as this environment has them; custom ones from the spec file's folder."""
    from osmo.tasktypes.registry import Resolver

    return Resolver([str(Path(file).parent)])


def _submit(args: argparse.Namespace) -> int:
    if args.runtime is not None and not args.dry_run:
        raise UsageError("--runtime kubernetes shows what would be created: add --dry-run")
    if args.dry_run and args.runtime == "kubernetes":
        return _pods(args)
    if args.dry_run:
        from osmo.spec import load_spec, render_spec

        sys.stdout.write(render_spec(args.file, set_values=args.set_values,
                                     set_strings=args.set_strings))
        load_spec(args.file, set_values=args.set_values, set_strings=args.set_strings,
                  set_env=args.set_env, types=_types(args.file),
                  allow_localpath=args.allow_localpath)
        return 0
    with _client(args) as client:
        wf_id = client.submit(args.file, set_values=args.set_values,
                              set_strings=args.set_strings, set_env=args.set_env, pool=args.pool,
                              no_cache=args.no_cache, reuse=args.reuse,
                              labels=_label_args(args.labels),
                              priority=args.priority, allow_localpath=args.allow_localpath)
        if args.format == "json" and not args.wait:
            print_json({"workflow_id": wf_id})
            return 0
        console.print(f"Workflow ID - {wf_id}", markup=False)
        return _wait(client, wf_id, args.format) if args.wait else 0


def _pods(args: argparse.Namespace) -> int:
    """``submit --dry-run --runtime kubernetes``: the objects the attempts would create."""
    from osmo.runtime.kubernetes.config import load_pool
    from osmo.spec import load_spec
    from osmo.worker.pods import pod_manifests

    spec = load_spec(args.file, set_values=args.set_values, set_strings=args.set_strings,
                     set_env=args.set_env, types=_types(args.file),
                     allow_localpath=args.allow_localpath)
    if args.task is not None and args.task not in {t.name for t in spec.all_tasks()}:
        raise UsageError(f"--task {args.task}: the workflow has no such task")
    items = pod_manifests(spec, load_pool(args.kubernetes_config), args.task,
                          priority=args.priority)
    print_json({"apiVersion": "v1", "kind": "List", "items": items})
    return 0


def _wait(client: Client, wf_id: str, fmt: str = "text") -> int:
    """Follow a workflow to its end with live progress; 0 iff COMPLETED."""
    if console.is_terminal and fmt == "text":
        with live_progress() as update:
            info = client.wait(wf_id, on_update=update, min_interval=0.2)
    else:
        seen: dict[str, str] = {}

        def show(i: WorkflowInfo) -> None:
            for t in i.tasks:
                if seen.get(t.name) != t.status.name and fmt == "text":
                    seen[t.name] = t.status.name
                    cached = " (cached)" if t.reused else ""
                    console.print(f"{safe(t.name)}: {t.status.name}{cached}", markup=False)

        info = client.wait(wf_id, on_update=show if fmt == "text" else None,
                           min_interval=0.2)
        if fmt == "text":
            console.print(workflow_header(info), markup=False)
            console.print(task_table(info.tasks))
    if fmt == "json":
        print_json(info_dict(info))
    elif (notice := reuse_notice(info)) is not None:
        console.print(notice, markup=False, soft_wrap=True)
    if not info.ok:
        raise WorkflowFailed(info.id, info.status.name)
    return 0


def _validate(args: argparse.Namespace) -> int:
    from osmo.spec import load_spec

    spec = load_spec(args.file, set_values=args.set_values, set_strings=args.set_strings,
                     set_env=args.set_env, types=_types(args.file),
                     allow_localpath=args.allow_localpath)
    console.print(f"{args.file}: valid workflow '{spec.name}' with "
                  f"{len(spec.all_tasks())} task(s) in {len(spec.groups)} group(s)", markup=False)
    return 0


def _query(args: argparse.Namespace) -> int:
    limit = args.limit if args.limit is not None or args.format == "json" else QUERY_LIMIT
    if limit is not None and limit < 0:
        raise UsageError(f"--limit must be 0 or more, not {limit}")
    with _client(args) as client:
        info = client.get(args.workflow_id, limit=limit,
                          statuses=[s.upper() for s in args.status])
    if args.format == "json":
        print_json(info_dict(info))
    else:
        console.print(workflow_header(info), markup=False)
        console.print()
        if info.tasks:
            console.print(task_table(info.tasks, verbose=args.verbose))
        if info.not_shown or args.status:
            console.print(not_shown_line(info), markup=False)
    return 0


def _list(args: argparse.Namespace) -> int:
    statuses = [s.upper() for s in args.status]
    with _client(args) as client:
        rows = client.list(statuses=statuses, name=args.name, limit=args.count,
                           labels=_label_args(args.labels))
    if args.format == "json":
        print_json([info_dict(r) for r in rows])
    elif rows:
        console.print(workflows_table(rows))
    else:
        console.print("no workflows", markup=False)
    return 0


def _logs(args: argparse.Namespace) -> int:
    if args.lines is not None and args.lines < 0:
        raise UsageError(f"--tail {args.lines}: give a number of lines from 0")
    since = None if args.since is None else since_time(args.since, time.time())
    with _client(args) as client:
        records = client.iter_logs(args.workflow_id, task=args.task, retry=args.retry,
                                   tail=args.lines, since=since, follow=args.follow,
                                   stream="stderr" if args.error else None)
        try:
            for record in records:  # printed as each chunk arrives: nothing is held
                sys.stdout.write(format_log(record) + "\n")
                if args.follow:
                    sys.stdout.flush()
            sys.stdout.flush()
        except BrokenPipeError:  # the reader stopped (`osmo logs ID | head`): so do we
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0


def since_time(text: str, now: float) -> float:
    """``--since`` in seconds since the epoch.

    ``text`` is a duration ago (``30s``, ``10m``, ``2h``, ``1d``) or an ISO time (local unless
    it names a zone).

    Raises:
        UsageError: neither.
    """
    from datetime import datetime

    from osmo.spec.units import parse_duration

    try:
        return now - parse_duration(text)
    except ValueError:
        pass
    try:
        return datetime.fromisoformat(text.strip()).timestamp()
    except ValueError:
        raise UsageError(f"--since {safe(text)}: give a duration ago (30s, 10m, 2h, 1d) or an "
                         "ISO time (2024-05-01T10:00)") from None


def _label_args(items: list[str]) -> dict[str, str]:
    """``--label K=V`` values → a dict (later wins); checked as the server checks them."""
    labels: dict[str, str] = {}
    for item in items:
        key, eq, value = item.partition("=")
        if not eq:
            raise UsageError(f"--label {safe(item)}: expected K=V")
        labels.update([check_label(key, value)])
    return labels


def _tag(args: argparse.Namespace) -> int:
    if not args.add and not args.remove:
        raise UsageError("osmo workflow tag: give --add TAG... and/or --remove TAG...")
    with _client(args) as client:
        tags = client.tag(args.workflow_id, add=args.add, remove=args.remove)
    if args.format == "json":
        print_json({"workflow_id": args.workflow_id, "tags": tags})
    else:
        console.print(f"Workflow {safe(args.workflow_id)} tags: "
                      f"{', '.join(map(safe, tags)) or '(none)'}", markup=False)
    return 0


def _events(args: argparse.Namespace) -> int:
    with _client(args) as client:
        events = client.events(args.workflow_id, task=args.task)
    if args.format == "json":
        print_json(events)
    elif events:
        console.print(events_text(events), markup=False, highlight=False, soft_wrap=True)
    return 0


def _cancel(args: argparse.Namespace) -> int:
    """Cancel each workflow named; one that cannot be cancelled does not stop the others."""
    code = 0
    with _client(args) as client:
        for wf_id in dict.fromkeys(args.workflow_ids):
            try:
                status = client.cancel(wf_id)
            except OsmoError as exc:
                print_error(f"{safe(wf_id)}: {exc}")
                code = max(code, exc.exit_code)
                continue
            console.print(f"Workflow {safe(wf_id)}: {status.name}", markup=False)
    return code


def _restart(args: argparse.Namespace) -> int:
    with _client(args) as client:
        wf_id = client.restart(args.workflow_id)
        console.print(f"Workflow ID - {wf_id}", markup=False)
        return _wait(client, wf_id) if args.wait else 0


def _spec(args: argparse.Namespace) -> int:
    from osmo.spec import dump_yaml, spec_from_dict

    with _client(args) as client:
        data = client.spec(args.workflow_id)
    sys.stdout.write(dump_yaml(spec_from_dict(data)))
    return 0


_VERBS: dict[str, Callable[[argparse.Namespace], int]] = {
    "submit": _submit,
    "validate": _validate,
    "query": _query,
    "status": _query,
    "list": _list,
    "logs": _logs,
    "events": _events,
    "tag": _tag,
    "cancel": _cancel,
    "restart": _restart,
    "spec": _spec,
    "exec": run_exec,
    "port-forward": run_forward,
    "server": run_server,
    "artifacts": run_artifacts,
    "lineage": run_lineage,
    "dataset": run_dataset,
    "credential": run_credential,
    "pool": run_pool,
    "resource": run_resource,
    "workers": run_resource,
    "plugins": run_plugins,
    "worker": run_worker,
    "health": run_health,
    "profile": run_profile,
    "eval": run_eval,
    "view": run_view,
    "token": run_token,
    "completion": run_completion,
}


def run(verb: str, args: argparse.Namespace) -> int:
    """Run one verb; OsmoError propagates to ``main`` for its exit code."""
    return _VERBS[verb](args)
