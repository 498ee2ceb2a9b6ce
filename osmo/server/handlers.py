"""The server's request handlers: one function per API verb, JSON in and JSON out.

Every request arrives with its caller's identity; ``handle`` routes it through the verb table
(``osmo.server.auth.API``: who may call which verb, and which handler serves it), which
checks the role first; cancel, restart and tag also check that a ``user`` submitted the
workflow (workflows record their submitter: ``osmo.store.submission.Submission``).

Mutating verbs (submit, cancel, restart) ask the engine with a typed request
(``osmo.server.requests``) and reply only after their changes are committed. Read verbs read
the store directly from the calling API thread. Handlers raise ``OsmoError`` subclasses for
the client's mistakes.
"""

from __future__ import annotations

import builtins
import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import replace
from enum import Enum
from typing import Any

from osmo.artifacts import ArtifactStore
from osmo.errors import NotFoundError, OsmoError, UsageError
from osmo.layout import Home
from osmo.names import (
    MAX_NAME,
    check_label,
    check_name,
    check_workflow_id,
    did_you_mean,
    shown,
)
from osmo.scheduler.types import PRIORITIES, CancelWorkflow
from osmo.server.artifact_handlers import ArtifactHandlers
from osmo.server.auth import Router, TokenHandlers, check_owner
from osmo.server.credentials import CredentialHandlers, check_task_credentials
from osmo.server.dataset_handlers import DatasetHandlers
from osmo.server.engine import Engine
from osmo.server.logview import last_progress, last_pull, read_logs
from osmo.server.requests import ListNodes, SubmitWorkflow, TagWorkflow, WaitReasons
from osmo.server.sessions import Sessions
from osmo.server.submitted import ClientTypes, check_no_localpath
from osmo.server.taskview import TaskView, spec_order
from osmo.server.workers import WorkerHub
from osmo.spec import spec_from_dict
from osmo.spec.parse import MAX_LABELS
from osmo.spec.stored import StoredSpec
from osmo.spec.typed import apply_resolved
from osmo.status import TaskStatus, WorkflowStatus
from osmo.store.sqlite import WorkflowRow
from osmo.store.submission import Submission
from osmo.transport.auth import Identity, Role
from osmo.transport.blobs import Asker
from osmo.transport.rpc import MAX_INT, Gate, ask_back, field, str_list
from osmo.transport.zenoh_link import Link
from osmo.worker.logs import STREAMS

__all__ = ["Handlers"]

log = logging.getLogger("osmo.server")

MAX_LIST = 1_000_000  # workflows one ``list`` may ask for
_WAITS = ("WAITING", "SCHEDULING")  # task statuses that have a reason to wait
_MAX_TEXT = 4096  # characters of a path, a pool or an artifact target in a request


# what ``ping`` shows admins only: paths and addresses of the server's host, and its host id
# (knowing it is how a worker proves it runs on this host: ``WorkerHub.register``)
_PRIVATE_INFO = ("home", "artifacts", "zenoh_config", "endpoint", "endpoints", "host_id")


def _asker_of(link: Link, gate: Gate) -> Callable[[Identity], Asker | None]:
    return lambda who: ask_back(link, gate, who.channel)


class Handlers:
    """Dispatches ``verb`` → handler. ``info`` is returned by ``ping``."""

    def __init__(self, engine: Engine, home: Home, info: dict[str, Any],
                 on_shutdown: Callable[[], None], workers: WorkerHub | None = None,
                 link: Link | None = None, gate: Gate | None = None,
                 tokens: TokenHandlers | None = None,
                 sessions: Sessions | None = None,
                 warm: Callable[[], builtins.list[dict[str, Any]]] | None = None) -> None:
        self._warm = warm  # the local pool's warm runners, now
        self._workers = workers  # the WorkerHub: its verbs, and worker status for pools
        self._engine = engine
        self._store = engine.store
        self._taskview = TaskView(self._store)
        self._home = home
        self._info = info
        self._on_shutdown = on_shutdown
        self._artifacts = ArtifactStore(home.artifacts)
        self._route = Router({
            "api": self, "workers": workers, "sessions": sessions, "tokens": tokens,
            "artifacts": ArtifactHandlers(self._store, self._artifacts, self._row),
            "datasets": DatasetHandlers(engine, self._artifacts,
                                        _asker_of(link, gate) if link and gate else None),
            "credentials": CredentialHandlers(self._store)})

    def handle(self, verb: str, request: dict[str, Any], who: Identity) -> Any:
        """Run the handler for ``verb`` as ``who`` (``osmo.server.auth.API`` names both).

        Raises:
            UsageError: an unknown verb.
            NotAllowed: ``who``'s role may not (``osmo.server.auth.authorize``).
        """
        return self._route(verb, request, who)

    def ping(self, _request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """The server's info, and who the caller is; paths only for an admin."""
        info = dict(self._info, identity={"name": who.name, "role": who.role.value})
        if who.role is not Role.ADMIN:
            for key in _PRIVATE_INFO:
                info.pop(key, None)
        return info

    # ------------------------------------------------------------------ mutating verbs

    def submit(self, request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """Create a workflow from a spec dict.

        Request: spec (rendered by the client, ``localpath`` files already read), pool?,
        filename?, no_cache?, reuse?, types? (``task -> ResolvedType`` of its custom ``module:attr``
        types, which the client imported from the spec's folder). The server reads no file
        and imports no code a client names (``osmo.server.submitted``); installed task types
        are resolved here, with this server's plugins. What was resolved (version,
        resources, folders) is kept with its stored spec (``osmo.spec.stored``). Outputs to
        reuse are for ``restart`` to give, never a request.
        """
        if "reused" in request or "reused_from" in request:
            raise UsageError("'reused' and 'reused_from' are set by `osmo restart` only")
        if "source" in request:
            raise UsageError("'source' is no longer accepted: the server reads no file a "
                             "client names; send the rendered 'spec' (the CLI and SDK do)")
        stored = StoredSpec(field(request, "spec", dict),
                            field(request, "filename", str, default=None, max_len=_MAX_TEXT),
                            field(request, "types", dict, default={}))
        priority = field(request, "priority", str, default="NORMAL", max_len=16).upper()
        if priority not in PRIORITIES:
            raise UsageError(f"priority must be one of {', '.join(PRIORITIES)}, not "
                             f"{shown(priority)}")
        no_cache, reuse = (field(request, k, bool, default=False) for k in ("no_cache", "reuse"))
        if no_cache and reuse:
            raise UsageError("--reuse and --no-cache contradict each other; give one")
        options = Submission(pool=field(request, "pool", str, default=None, max_len=_MAX_TEXT),
                             priority=priority, labels=_labels(request, "labels"),
                             no_cache=no_cache, reuse=reuse, submitted_by=who.name)
        return self._admit(stored, options, {})

    def _admit(self, stored: StoredSpec, options: Submission,
               reused: dict[str, str]) -> dict[str, Any]:
        """Check ``stored`` (parsed once, here) and have the engine create its workflow.

        The spec's types are resolved with this server's plugins, custom ones as the client
        described them (``osmo.server.submitted``); the workflow keeps what they resolved to.
        """
        check_no_localpath(stored.data)
        types = ClientTypes(stored.types, stored.data)
        spec = apply_resolved(spec_from_dict(stored.data, filename=stored.source, types=types),
                              types.described)
        check_task_credentials(spec, self._store)
        labels = {**spec.labels, **options.labels}
        if len(labels) > MAX_LABELS:
            raise UsageError(f"a workflow has at most {MAX_LABELS} labels; with --label this "
                             f"one would have {len(labels)}")
        options = replace(options, pool=options.pool or spec.pool, labels=labels)
        return {"workflow_id": self._engine.ask(SubmitWorkflow(
            spec, stored.resolved_as(spec), options, reused))}

    def workflow_tag(self, request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """Add and remove a workflow's tags (names); replies with its tags after the change."""
        row = self._own(self._row(request.get("workflow_id")), who, "workflow_tag")
        add, remove = ([check_name(t, "workflow tag") for t in str_list(request, key)]
                       for key in ("add", "remove"))
        tags = self._engine.ask(TagWorkflow(row.id, tuple(add), tuple(remove)))
        return {"workflow_id": row.id, "tags": tags}

    def cancel(self, request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """Cancel a workflow; a no-op for one already ended."""
        row = self._own(self._row(request.get("workflow_id")), who, "cancel")
        self._engine.ask(CancelWorkflow(row.id))
        return {"workflow_id": row.id, "status": self._row(row.id).status}

    def restart(self, request: dict[str, Any], who: Identity) -> dict[str, Any]:
        """Submit the same spec again, reusing the outputs of tasks that completed."""
        row = self._own(self._row(request.get("workflow_id"), with_spec=True), who, "restart")
        if not WorkflowStatus[row.status].terminal:
            raise UsageError(f"workflow {row.id} is still {row.status}; "
                             f"cancel it first (`osmo cancel {row.id}`)")
        reused = {t["name"]: t["output"] for t in self._store.tasks(row.id)
                  if t["status"] == "COMPLETED" and t.get("output")}
        return self._admit(row.spec, replace(row.options, submitted_by=who.name,
                                             reused_from=row.id, tags=()), reused)

    @staticmethod
    def _own(row: WorkflowRow, who: Identity, verb: str) -> WorkflowRow:
        """``row`` if ``who`` may change it: an admin, or the user who submitted it.

        Raises:
            NotAllowed: another user's workflow (logged once).
        """
        check_owner(row.id, row.options.submitted_by, who, verb)
        return row

    def shutdown(self, _request: dict[str, Any]) -> dict[str, Any]:
        """Stop the server (after replying)."""
        self._on_shutdown()
        return {"pid": os.getpid()}

    # ------------------------------------------------------------------ read verbs

    def get(self, request: dict[str, Any]) -> dict[str, Any]:
        """A workflow's state and its tasks' states (``waiting``: and why waiting tasks wait).

        A placed task whose node said its cluster holds the attempt (``node_wait``: a pod
        Pending, a Slurm job PENDING) has that reason as its ``waiting``, whatever ``waiting``
        asks (it is stored, it costs nothing).

        With ``limit`` (the most tasks to return) or ``statuses`` (only tasks with one of
        them), the reply also holds ``counts`` (status → tasks) and ``matched`` (tasks with
        the statuses asked for), and only the first ``limit`` of those in spec order are
        decoded and returned (``osmo.server.taskview``): fast on a 100,000-task workflow.
        """
        reasons = field(request, "waiting", bool, default=False)
        limit = field(request, "limit", int, default=None, what="the count of tasks to show")
        statuses = _statuses(request, TaskStatus, "task status")
        extra: dict[str, Any] = {}
        if limit is None and statuses is None:
            row = self._row(request.get("workflow_id"), with_spec=True)
            tasks = _ordered_tasks(row, self._store.tasks(row.id))
        else:
            if limit is not None and limit < 0:
                raise UsageError(f"the count of tasks to show must be 0 or more, not {limit}")
            row = self._row(request.get("workflow_id"))
            page = self._taskview.page(row.id, limit=limit, statuses=statuses or (),
                                       spec=lambda: self._row(row.id, with_spec=True).spec.data)
            tasks, extra = page.tasks, {"counts": page.counts, "matched": page.matched}
        for task in tasks:  # typed tasks report progress as log lines, pulls too: the latest
            if task.get("node_wait") and task.get("status") in ("RUNNING", "INITIALIZING"):
                # its node's cluster holds it (a pod Pending, a Slurm job PENDING)
                task["waiting"] = {"reason": task["node_wait"], "since": task.get(
                    "node_wait_since"), "fails_at": None}
            if task.get("status") in ("RUNNING", "INITIALIZING"):
                dirs = self._home.attempt(row.id, task["name"], int(task.get("retry", 0)))
                task["progress"] = (last_progress(dirs.log) if task["status"] == "RUNNING"
                                    else last_pull(dirs.log, time.time()))
        if reasons and any(t.get("status") in _WAITS for t in tasks):  # only then: it costs
            # a page of a big workflow does not wait long for a busy engine's reasons
            self._add_reasons(row.id, tasks, timeout=0.5 if extra else 5)
        return {"workflow": _workflow_dict(row), "tasks": tasks, **extra}

    def _add_reasons(self, workflow_id: str, tasks: builtins.list[dict[str, Any]],
                     timeout: float) -> None:
        """Say why each waiting task waits; a busy or stopped engine leaves them out."""
        try:
            names = frozenset(t["name"] for t in tasks if t.get("status") in _WAITS)
            reasons = self._engine.ask(WaitReasons(workflow_id, names), timeout=timeout)
        except (OsmoError, TimeoutError) as exc:
            log.warning("no waiting reasons for %s: %s", workflow_id, exc or "engine busy")
            return
        for task in tasks:
            if task["name"] in reasons:
                task["waiting"] = vars(reasons[task["name"]])

    def status(self, request: dict[str, Any]) -> dict[str, Any]:
        """Only the workflow's own state (cheap: for waiting on big workflows)."""
        return _workflow_dict(self._row(request.get("workflow_id")))

    def list(self, request: dict[str, Any]) -> list[dict[str, Any]]:
        """Workflows newest first; filters: statuses, name, limit."""
        rows = self._store.workflows(statuses=_statuses(request),
                                     name=field(request, "name", str, default=None,
                                                max_len=MAX_NAME),
                                     limit=_limit(request), labels=_labels(request, "labels"))
        return [_workflow_dict(r) for r in rows]

    def logs(self, request: dict[str, Any]) -> dict[str, Any]:
        """The next chunk of a workflow's log records after a cursor (``more``: call again).

        ``tail``, ``since`` and ``stream`` as ``osmo logs``; see ``osmo.server.logview``.
        """
        row = self._row(request.get("workflow_id"))
        task, retry = self._attempt(row, request)
        tail = field(request, "tail", int, default=None)
        if tail is not None and tail < 0:
            raise UsageError(f"'tail' is a number of records from 0, not {tail}")
        stream = field(request, "stream", str, default=None)
        if stream is not None and stream not in STREAMS:
            raise UsageError(f"'stream' is one of {', '.join(STREAMS)}, not {shown(stream)}")
        return read_logs(self._store, row, task=task, retry=retry, cursor=_cursor(request),
                         tail=tail, since=_since(request), stream=stream)

    def events(self, request: dict[str, Any]) -> builtins.list[dict[str, Any]]:
        """The workflow's scheduling timeline, oldest first (optionally of one task).

        Each event is a status change of the workflow (``task`` None) or of a task retry, with
        its message (why it waits, failed or was retried) and, for a retry, the node its
        attempt was placed on (None until placed).
        """
        row = self._row(request.get("workflow_id"))
        task, _ = self._attempt(row, request)
        nodes = {(a.task, a.retry): a.node_id for a in self._store.attempts(row.id, task)}
        return [{"at": e["at"], "task": e["task"], "retry": e["retry"], "status": e["status"],
                 "message": e["message"], "node": nodes.get((e["task"], e["retry"]))}
                for e in self._store.transitions(row.id)
                if task is None or e["task"] == task]

    def spec(self, request: dict[str, Any]) -> dict[str, Any]:
        """The stored (rendered) spec of a workflow, as a dict."""
        return {"spec": self._row(request.get("workflow_id"), with_spec=True).spec.data}

    def pools(self, _request: dict[str, Any]) -> builtins.list[dict[str, Any]]:
        """Known nodes with their pool, platform, sandbox and capacity used/total.

        ``platforms``: each platform the node serves (one, or a cluster node's several),
        with its own capacity used/total.

        ``sandbox`` is ``bwrap`` or ``none``; ``sandbox_why`` says why not, in a few words
        (None when sandboxed, or from a worker too old to say). ``warm``: the node's warm
        runners (type, pid, rss, started, running; a remote worker's as of its last beat).
        """
        remote = {w["id"]: w for w in self._workers.workers()} if self._workers else {}
        out = []
        for node, used, by_platform in self._engine.ask(ListNodes()):
            worker = remote.get(node.id, {})
            about = worker or self._info
            sandbox = node.labels.get("sandbox", "none")
            out.append({"node": node.id, "pool": node.pool, "platform": node.platform,
                        "status": worker.get("status", "online"),
                        "kind": "remote" if worker else "local", "sandbox": sandbox,
                        "sandbox_why": about.get("sandbox_why") if sandbox == "none" else None,
                        "runtime": about.get("runtime"),
                        "warm": worker.get("warm") if worker else
                        self._warm() if self._warm is not None else None,
                        "total": vars(node.capacity), "used": vars(used),
                        "platforms": {p: {"total": vars(node.offers(p) or node.capacity),
                                          "used": vars(by_platform.get(p, used))}
                                      for p in node.served()}})
        return out

    def _attempt(self, row: WorkflowRow, request: dict[str, Any]) -> tuple[str | None,
                                                                          int | None]:
        """The ``task`` and ``retry`` a request names, checked to exist in ``row``."""
        task = field(request, "task", str, default=None)
        retry = field(request, "retry", int, default=None)
        if retry is not None and retry < 0:
            raise UsageError(f"a retry is a number from 0, not {retry}")
        if task is None:
            return None, retry
        check_name(task, "task name")
        latest = {t["name"]: int(t.get("retry", 0)) for t in self._store.tasks(row.id)}
        if task not in latest:
            raise NotFoundError(f"no task '{task}' in {row.id}{did_you_mean(task, latest)}")
        if retry is not None and not 0 <= retry <= latest[task]:
            raise NotFoundError(f"task '{task}' of {row.id} has no retry {retry} (it has "
                                f"retries 0 to {latest[task]})")
        return task, retry

    def _row(self, workflow_id: object, *, with_spec: bool = False) -> WorkflowRow:
        workflow_id = check_workflow_id(workflow_id)
        row = self._store.workflow(workflow_id, with_spec=with_spec)
        if row is None:
            near = [r.id for r in self._store.workflows(name=workflow_id.rsplit("-", 1)[0],
                                                        limit=5)]
            hint = f" (did you mean {', '.join(near)}?)" if near else ""
            raise NotFoundError(f"no workflow '{workflow_id}'{hint}")
        return row


def _statuses(request: dict[str, Any], kind: type[Enum] = WorkflowStatus,
              what: str = "status") -> builtins.list[str] | None:
    """The request's ``statuses``, each a member of ``kind`` (None: not given)."""
    statuses = str_list(request, "statuses")
    for status in statuses:
        if status not in kind.__members__:
            raise UsageError(f"unknown {what} {shown(status)}; the statuses are "
                             f"{', '.join(kind.__members__)}")
    return statuses or None


def _limit(request: dict[str, Any]) -> int | None:
    what = "the count of workflows to list"
    limit: int | None = field(request, "limit", int, default=None, what=what)
    if limit is not None and not 1 <= limit <= MAX_LIST:
        raise UsageError(f"{what} must be from 1 to {MAX_LIST}, not {limit}")
    return limit


def _since(request: dict[str, Any]) -> float | None:
    """A request's ``since``: seconds since the epoch (a number), or None."""
    since = request.get("since")
    if since is None:
        return None
    if not isinstance(since, int | float) or isinstance(since, bool) \
            or not math.isfinite(since):
        raise UsageError(f"'since' must be a time in seconds since the epoch, not "
                         f"{shown(since)}")
    return float(since)


def _cursor(request: dict[str, Any]) -> dict[str, Any] | None:
    """A log cursor as ``logview`` gave it out: ``{files: {attempt: offset}, seq}``."""
    cursor = field(request, "cursor", dict, default=None)
    if cursor is None:
        return None
    files = field(cursor, "files", dict, default={}, what="'cursor.files'")
    seq = field(cursor, "seq", int, default=0, what="'cursor.seq'")
    if seq < 0 or not all(isinstance(k, str) and type(v) is int and 0 <= v <= MAX_INT
                          for k, v in files.items()):
        raise UsageError("'cursor' is not one this server gave out; start again without it")
    return {"files": files, "seq": seq}


def _workflow_dict(row: WorkflowRow) -> dict[str, Any]:
    state = dict(row.state) or {"id": row.id, "name": row.name, "status": row.status,
                                "submitted_at": row.submitted_at}
    opts = row.options
    state.update(pool=opts.pool, reused_from=opts.reused_from, submitted_by=opts.submitted_by,
                 labels=dict(opts.labels), tags=list(opts.tags))
    return state


def _labels(request: dict[str, Any], key: str) -> dict[str, str]:
    """A request's ``{key: value}`` labels, each checked (``osmo.names.check_label``)."""
    labels = field(request, key, dict, default={})
    if len(labels) > MAX_LABELS:
        raise UsageError(f"at most {MAX_LABELS} labels, not {len(labels)}")
    return dict(check_label(k, v) for k, v in labels.items())


def _ordered_tasks(row: WorkflowRow, tasks: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Tasks in spec order (groups, then tasks within a group)."""
    order = {name: i for i, name in enumerate(spec_order(row.spec.data))}
    return sorted(tasks, key=lambda t: order.get(t["name"], len(order)))
