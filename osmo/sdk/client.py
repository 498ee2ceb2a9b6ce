"""``osmo.Client``: submit, inspect, follow and control workflows from Python.

The client validates and renders specs locally (so ``localpath`` files are read where the
spec lives), sends the model as a plain dict, and talks to the server over zenoh. It is
what the CLI uses too; every CLI verb is a thin layer over a method here.
"""

from __future__ import annotations

import builtins
import contextlib
import json
import os
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, TypeAlias

from osmo.errors import UsageError
from osmo.names import check_name, check_tag, check_workflow_id, parse_ref
from osmo.sdk.connect import Connection, connect
from osmo.sdk.records import (
    EventInfo,
    LogRecord,
    TaskInfo,
    TaskWaiting,
    WorkflowInfo,
    log_record,
    workflow_info,
)

if TYPE_CHECKING:  # the spec package (YAML, Jinja) loads only when a spec is handled here
    from osmo.sdk.transfer import Progress
    from osmo.spec import Workflow
    from osmo.spec.model import WorkflowSpec
from osmo.status import WorkflowStatus
from osmo.transport.streams import SessionGrant
from osmo.transport.zenoh_link import Link

__all__ = ["Client", "EventInfo", "LogRecord", "TaskInfo", "TaskWaiting", "WorkflowInfo"]

SpecLike: TypeAlias = "str | os.PathLike[str] | dict[str, Any] | WorkflowSpec | Workflow"


class Client:
    """A connection to an osmo server.

    A read is named by what it returns (``artifacts``, ``dataset``), an action by verb and
    object (``get_artifact``, ``tag_dataset``); the API verbs are ``<object>_<verb>``.

    Args:
        server: zenoh endpoint of a server (``tcp/host:7447``); default: ``OSMO_SERVER`` or
            the local server of ``home``, started in the background if needed.
        home: the osmo home of the local server (default ``OSMO_HOME``).
        autostart: start a local server when none runs (default True).
        token: the API token to send (default: ``OSMO_TOKEN``, the profile's ``token``, or
            for the home's own server its owner's admin token; see ``osmo.sdk.connect``).
    """

    def __init__(self, server: str | None = None, *, home: str | os.PathLike[str] | None = None,
                 autostart: bool = True, token: str | None = None) -> None:
        self._conn: Connection = connect(server, home, autostart=autostart, token=token)
        self._home = self._conn.home.root  # never read by a spec's localpath

    def close(self) -> None:
        """Close the connection."""
        self._conn.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _call(self, verb: str, *, timeout: float | None = None, **request: Any) -> Any:
        if "workflow_id" in request:  # checked here, so a mistyped id never leaves this host
            check_workflow_id(request["workflow_id"])
        return self._conn.api.call(verb, request, timeout=timeout)

    # ------------------------------------------------------------------ submit & control

    def submit(self, spec: SpecLike, *, set_values: Sequence[str] = (),
               set_strings: Sequence[str] = (), set_env: Sequence[str] = (),
               pool: str | None = None, no_cache: bool = False,
               labels: Mapping[str, str] | None = None, priority: str = "NORMAL",
               allow_localpath: Sequence[str | os.PathLike[str]] = (),
               reuse: bool = False) -> str:
        """Validate ``spec`` (a path, a dict, a model or a builder) and submit it.

        A task whose definition and input contents match an earlier success may reuse its
        outputs instead of running (marked cached): typed tasks and tasks whose output another
        task takes do by default, a bare command task that feeds none does not. ``cache:``
        in the spec (task, then workflow) overrides that default, and so does ``reuse``
        (every task whose spec says nothing); ``no_cache`` runs every task.
        ``labels`` are merged over the spec's ``workflow.labels`` (``--label k=v``);
        ``priority`` is HIGH, NORMAL or LOW (placement order when resources are short).
        ``files: localpath:`` reads only inside the spec's folder tree and the
        ``allow_localpath`` folders, never in an osmo home (``osmo.spec.localfiles``).

        Returns:
            the new workflow's id (``<name>-<N>``).

        Raises:
            SpecError: the spec is invalid (nothing was created).
            SubmitError: the server cannot run it (e.g. no pool fits a task).
        """
        from osmo.spec import spec_to_dict

        model, filename = _to_model(spec, set_values, set_strings, set_env,
                                    _Localpath(tuple(allow_localpath), (self._home,)))
        types = {t.name: t.resolved.to_dict() for t in model.all_tasks() if t.resolved}
        result = self._call("submit", spec=spec_to_dict(model), pool=pool, filename=filename,
                            no_cache=no_cache, types=types, labels=dict(labels or {}),
                            priority=priority, reuse=reuse)
        return str(result["workflow_id"])

    def cancel(self, workflow_id: str) -> WorkflowStatus:
        """Cancel a workflow; returns its status after the cancel was committed."""
        return WorkflowStatus[self._call("cancel", workflow_id=workflow_id)["status"]]

    def tag(self, workflow_id: str, *, add: Sequence[str] = (),
            remove: Sequence[str] = ()) -> builtins.list[str]:
        """Add and remove a workflow's tags; returns its tags after the change."""
        reply = self._call("workflow_tag", workflow_id=workflow_id, add=list(add),
                           remove=list(remove))
        return builtins.list(reply["tags"])

    def restart(self, workflow_id: str) -> str:
        """Submit a finished workflow again, reusing outputs of its completed tasks."""
        return str(self._call("restart", workflow_id=workflow_id)["workflow_id"])

    # ------------------------------------------------------------------ read

    def get(self, workflow_id: str, *, waiting: bool = True, limit: int | None = None,
            statuses: Sequence[str] = ()) -> WorkflowInfo:
        """The workflow's current status and tasks.

        Args:
            workflow_id: the workflow.
            waiting: also say why each waiting task waits (``TaskInfo.waiting``); the
                server's scheduler computes that, so a frequent poller may leave it out.
            limit: return only the first ``limit`` tasks (spec order); the info's
                ``counts`` then holds how many tasks have each status and ``not_shown``
                how many were left out. Fast on a workflow of 100,000 tasks.
            statuses: return only tasks with one of these statuses (``counts`` as above).
        """
        reply = self._call("get", workflow_id=workflow_id, waiting=waiting, limit=limit,
                           statuses=[getattr(s, "name", s) for s in statuses] or None)
        return workflow_info(reply["workflow"], reply["tasks"], reply.get("counts"),
                             reply.get("matched"))

    def list(self, *, statuses: Sequence[str] = (), name: str | None = None,
             limit: int | None = None,
             labels: Mapping[str, str] | None = None) -> builtins.list[WorkflowInfo]:
        """Workflows, newest first; ``labels``: only those with every one of these labels."""
        rows = self._call("list", statuses=list(statuses) or None, name=name, limit=limit,
                          labels=dict(labels or {}) or None)
        return [workflow_info(r) for r in rows]

    def spec(self, workflow_id: str) -> dict[str, Any]:
        """The rendered spec the workflow was submitted with."""
        return dict(self._call("spec", workflow_id=workflow_id)["spec"])

    def create_token(self, name: str, role: str = "user", *,
                     pools: Sequence[str] = ()) -> str:
        """A new API token ``name`` with ``role`` (admin only); returned once, never again.

        A worker token names the ``pools`` its workers may serve (``"*"``: every pool).
        """
        return str(self._call("token_create", name=name, role=role,
                              pools=list(pools))["token"])

    def tokens(self) -> builtins.list[dict[str, Any]]:
        """Every token's name, role, pools, created and revoked times (admin only)."""
        return builtins.list(self._call("token_list"))

    def revoke_token(self, name: str) -> None:
        """Revoke token ``name``: its next request is refused (admin only)."""
        self._call("token_revoke", name=name)

    def pools(self) -> builtins.list[dict[str, Any]]:
        """Nodes of the server's pools with capacity used/total."""
        return builtins.list(self._call("pools"))

    def logs(self, workflow_id: str, *, task: str | None = None, retry: int | None = None,
             tail: int | None = None, stream: str | None = None,
             since: float | None = None) -> builtins.list[LogRecord]:
        """All log records of a workflow so far, as a list.

        The arguments are :meth:`iter_logs`'s; it holds none of them: use it for big logs.
        """
        return builtins.list(self.iter_logs(workflow_id, task=task, retry=retry, tail=tail,
                                            stream=stream, since=since))

    def events(self, workflow_id: str, *, task: str | None = None) -> builtins.list[EventInfo]:
        """The workflow's scheduling timeline, oldest first (optionally of one task)."""
        return [EventInfo(e["at"], e["task"], e["retry"], e["status"], e["message"], e["node"])
                for e in self._call("events", workflow_id=workflow_id, task=task)]

    def iter_logs(self, workflow_id: str, *, task: str | None = None,
                  retry: int | None = None, tail: int | None = None,
                  stream: str | None = None, since: float | None = None,
                  follow: bool = False, interval: float = 0.25) -> Iterator[LogRecord]:
        """Yield a workflow's log records in time order, as the server sends them.

        One request per chunk (256 KiB of log): nothing is held here or on the server.

        Args:
            workflow_id: the workflow.
            task: only this task's records.
            retry: only this retry's records.
            tail: only the last N records (after the other filters; None or 0: all).
            stream: only this stream (``stdout``, ``stderr`` or ``osmo``).
            since: only records written at or after this time (seconds since the epoch).
            follow: go on yielding records as they are written, until the workflow ends.
            interval: with ``follow``, the longest wait between looks when nothing changes.
        """
        cursor: dict[str, Any] | None = None
        while True:
            reply = self._call("logs", workflow_id=workflow_id, task=task, retry=retry,
                               cursor=cursor, tail=tail if cursor is None else None,
                               since=since, stream=stream)
            cursor = reply["cursor"]
            yield from (r for r in map(log_record, reply["records"])
                        if stream is None or r.stream == stream)
            if reply.get("more"):
                continue
            if not follow or reply["done"]:
                return
            self._wait_change(workflow_id, interval)

    def follow_logs(self, workflow_id: str, *, task: str | None = None,
                    retry: int | None = None, interval: float = 0.25,
                    stream: str | None = None) -> Iterator[LogRecord]:
        """Yield log records as they are written, until the workflow has ended.

        :meth:`iter_logs` with ``follow=True``.
        """
        return self.iter_logs(workflow_id, task=task, retry=retry, stream=stream,
                              follow=True, interval=interval)

    def wait(self, workflow_id: str, *, timeout: float | None = None,
             on_update: Callable[[WorkflowInfo], None] | None = None,
             min_interval: float = 0.05) -> WorkflowInfo:
        """Block until the workflow is terminal; returns its final info.

        Wakes on the server's signed change notices (zenoh subscription) and re-reads the status
        (at most every ``min_interval`` seconds since the last read, so a busy workflow costs
        the server little, and a notice after a quiet spell is read at once); also re-reads
        at least every second in case a notice was missed. A notice that tells the
        workflow's end (``osmo.server.notices``) is read at once, interval or not.
        ``on_update`` gets the full workflow (with tasks) at a wake, but no more often
        than its reads cost: a read that took T seconds waits 9 T before the next, so the
        reads of a large workflow (25 µs of the server's time a task) take at most about a
        tenth of the time.

        Raises:
            TimeoutError: ``timeout`` seconds passed first.
        """
        changed, ended = threading.Event(), threading.Event()
        api = self._conn.api
        api.channel()  # learn the server's notice key first

        def on_notice(key: str, payload: bytes, signature: bytes | None) -> None:
            if api.verifier is None or not api.verifier.notice(key, payload, signature):
                return  # a notice a peer made up wakes nobody
            with contextlib.suppress(ValueError, AttributeError):
                if json.loads(payload).get("ended") is True:
                    ended.set()
            changed.set()

        sub = self._conn.link.subscribe_raw(self._conn.link.key("events", workflow_id),
                                            on_notice)
        deadline = None if timeout is None else time.monotonic() + timeout
        full_after = 0.0  # when on_update may have the next full read
        try:
            while True:
                changed.clear()
                shown = on_update is not None and time.monotonic() >= full_after
                if on_update is not None and shown:
                    began = time.monotonic()  # (no waiting reasons: they cost the engine)
                    info = self.get(workflow_id, waiting=False)
                    full_after = time.monotonic() + 9 * (time.monotonic() - began)
                    on_update(info)
                status = WorkflowStatus[self._call("status", workflow_id=workflow_id)["status"]]
                if status.terminal:
                    final = self.get(workflow_id)
                    if on_update is not None and not shown:  # the end is always shown
                        on_update(final)
                    return final
                if deadline is not None and time.monotonic() > deadline:
                    raise TimeoutError(f"workflow {workflow_id} still {status.name}")
                read = time.monotonic()
                changed.wait(timeout=1.0)
                pause = min_interval - (time.monotonic() - read)
                if pause > 0:  # coalesce bursts of notices into one re-read; not an end
                    ended.wait(pause)
        finally:
            sub.close()

    def _wait_change(self, workflow_id: str, interval: float) -> None:
        time.sleep(interval)

    # ------------------------------------------------------------------ artifacts & lineage

    def lineage(self, target: str, *, downstream: bool = False) -> dict[str, Any]:
        """The lineage graph of an artifact.

        A target is ``sha256:<digest>`` (a file or a whole output) or ``WORKFLOW_ID:TASK[:PATH]``.
        See ``osmo.server.lineage_query`` for its shape.
        """
        return dict(self._call("lineage", target=target, downstream=downstream))

    def artifacts(self, workflow_id: str, task: str | None = None) -> builtins.list[dict[str, Any]]:
        """Promoted outputs of a workflow with their files (path, digest, size)."""
        return builtins.list(self._call("artifact_list", workflow_id=workflow_id, task=task))

    def get_artifact(self, target: str, dest: str | os.PathLike[str], *,
                     on_progress: Progress | None = None) -> builtins.list[str]:
        """Write a target's files, verified, into ``dest`` on this machine.

        They are fetched from the server, wherever it runs. Returns the written paths.
        ``on_progress(done, total)`` hears of the bytes fetched (``osmo.sdk.transfer``).
        """
        from osmo.sdk import transfer

        reply = self._call("artifact_get", target=target)
        from osmo.artifacts import Manifest

        written = transfer.download(self._conn.api, self.ping(), Manifest.from_json(
            reply["body"]), Path(dest).absolute(), only=reply.get("only"),
                                    on_progress=on_progress, home=self._conn.home)
        return [str(p) for p in written]

    def gc_artifacts(self) -> tuple[int, int]:
        """Remove unreferenced blobs; returns (count, bytes)."""
        reply = self._call("artifact_gc")
        return int(reply["removed"]), int(reply["bytes"])

    # ------------------------------------------------------------------ datasets

    def datasets(self, name: str | None = None) -> builtins.list[dict[str, Any]]:
        """Dataset versions (of one dataset), newest first."""
        if name is not None:
            check_name(name, "dataset name")
        return builtins.list(self._call("dataset_list", name=name))

    def dataset(self, ref: str) -> dict[str, Any]:
        """One version (``NAME[:TAG_OR_VERSION]``, default newest) with its files."""
        parse_ref(ref)
        return dict(self._call("dataset_info", ref=ref))

    def tag_dataset(self, ref: str, tag: str) -> dict[str, Any]:
        """Point ``tag`` at the version ``ref`` names."""
        parse_ref(ref)
        return dict(self._call("dataset_tag", ref=ref, tag=check_tag(tag)))

    def download_dataset(self, ref: str, dest: str | os.PathLike[str], *,
                         regex: str | None = None,
                         on_progress: Progress | None = None) -> builtins.list[str]:
        """Write a version's files, verified, into ``dest`` on this machine.

        Returns the written paths. ``on_progress(done, total)`` hears of the bytes fetched.
        """
        from osmo.artifacts import Manifest
        from osmo.sdk import transfer

        parse_ref(ref)
        reply = self._call("dataset_download", ref=ref, regex=regex)
        written = transfer.download(self._conn.api, self.ping(),
                                    Manifest.from_json(reply["manifest"]), Path(dest).absolute(),
                                    on_progress=on_progress, home=self._conn.home)
        return [str(p) for p in written]

    def upload_dataset(self, name: str, path: str | os.PathLike[str], *,
                       metadata: dict[str, str] | None = None,
                       on_progress: Progress | None = None) -> int:
        """Make a new version of ``name`` from a folder on this machine; returns the version.

        A copy is sent; your files stay as they are. ``on_progress(done, total)`` hears of
        the bytes the server pulls, and of the whole when it has the version.
        """
        from osmo.sdk import transfer

        check_name(name, "dataset name")
        folder = Path(path).absolute()
        if not folder.is_dir():
            raise UsageError(f"cannot upload '{folder}': not a folder")
        offer = transfer.upload(self._conn.api, folder, on_progress, home=self._conn.home)
        try:
            reply = self._call("dataset_upload", name=name, manifest=offer.manifest.to_json(),
                               source=offer.source, metadata=metadata or {}, timeout=3600)
        finally:
            offer.close()
        if on_progress is not None:
            on_progress(offer.size, offer.size)
        return int(reply["version"])

    # ------------------------------------------------------------------ credentials

    def set_credential(self, name: str, payload: dict[str, str]) -> None:
        """Store a named secret on the server (e.g. ``s3`` with endpoint/access_key/...)."""
        self._call("credential_set", name=name, payload=payload)

    def credentials(self) -> builtins.list[dict[str, Any]]:
        """Stored credentials: names and keys, never values."""
        return builtins.list(self._call("credential_list"))

    def delete_credential(self, name: str) -> None:
        """Remove a stored credential."""
        self._call("credential_delete", name=name)

    def open_session(self, verb: str, **request: Any) -> tuple[SessionGrant, Link]:
        """Open an interactive session: ``exec_open`` or ``forward_open``.

        Returns its grant and the link its stream runs on (``osmo.transport.streams``;
        ``osmo.cli.interactive`` drives both ends of it).

        Raises:
            NotFoundError: no such workflow or task. NotAllowed: not the caller's workflow.
            UsageError: the task is not running.
        """
        reply = self._call(verb, **request)
        return SessionGrant.from_dict(reply["grant"]), self._conn.link

    def ping(self) -> dict[str, Any]:
        """The server's info (endpoint, pid, home)."""
        return dict(self._call("ping"))

    def shutdown(self) -> None:
        """Ask the server to stop."""
        self._call("shutdown")


class _Localpath(NamedTuple):
    """Where a spec's ``localpath`` may read besides its folder, and where never."""

    allow: tuple[str | os.PathLike[str], ...]
    deny: tuple[str | os.PathLike[str], ...]


def _to_model(spec: SpecLike, set_values: Sequence[str], set_strings: Sequence[str],
              set_env: Sequence[str], local: _Localpath) -> tuple[WorkflowSpec, str]:
    """The validated model and its file name.

    Task types are resolved here too (params checked with positions); custom ``module:attr`` types
    are imported from the spec file's folder, or the current folder for builders and dicts.
    """
    from osmo.spec import Workflow, load_spec, spec_from_dict
    from osmo.spec.model import WorkflowSpec
    from osmo.tasktypes.registry import Resolver

    if isinstance(spec, WorkflowSpec):
        return spec, "<model>"
    if isinstance(spec, Workflow):
        return spec_from_dict(spec.to_dict(), filename="<builder>",
                              types=Resolver([os.getcwd()])), "<builder>"
    if isinstance(spec, dict):
        text = json.dumps(spec)  # JSON is YAML: the one loader validates dicts too
        return load_spec(text=text, filename="<dict>", set_values=set_values,
                         set_strings=set_strings, set_env=set_env,
                         types=Resolver([os.getcwd()]), allow_localpath=local.allow,
                         deny_localpath=local.deny), "<dict>"
    if isinstance(spec, (str, os.PathLike)):
        path = Path(spec)
        return load_spec(path, set_values=set_values, set_strings=set_strings,
                         set_env=set_env, types=Resolver([str(path.parent)]),
                         allow_localpath=local.allow, deny_localpath=local.deny), str(path)
    raise UsageError(f"cannot submit a {type(spec).__name__}; pass a path, dict or Workflow")
