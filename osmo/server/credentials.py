"""Credentials: named secrets stored on the server, for data URLs and for tasks.

``osmo credential set NAME --payload key=value ...`` stores one; values never leave the
server through the API (``list`` shows names and keys only) and never reach logs. A data URL
picks its credential by name: for ``s3://BUCKET/...`` the credential called
``s3://BUCKET``, else the one called ``s3`` (keys: ``endpoint``, ``access_key``,
``secret_key``, ``region``, ``session_token``). ``file://`` URLs need none.

A task names credentials in ``credentials:`` (``NAME: {ENV: key}`` sets environment
variables, ``NAME: /path`` mounts every key as a file; see ``osmo.worker.secrets``).
``check_task_credentials`` refuses a submission whose credentials or keys do not exist; the
values are read from the store only when an attempt is prepared, so a credential updated
after submit is used by later attempts. The worker masks the values in the task's logs.
Only names and key names reach the spec, the run record, lineage and the cache fingerprint.

Credentials are stored in the state database (``OSMO_HOME/state.db``, readable only by the
server's user).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

from osmo.errors import NotFoundError, SubmitError, UsageError
from osmo.names import shown
from osmo.spec.model import TaskSpec, WorkflowSpec
from osmo.store.sqlite import Store
from osmo.transport.rpc import field, str_map
from osmo.worker.secrets import unusable_file_name

__all__ = ["CredentialHandlers", "check_task_credentials", "url_credential"]

_MAX_NAME = 256  # an S3 bucket name is at most 63; room for a prefix
_NAME_OK = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789-_.:/")


def url_credential(store: Store) -> Callable[[str], dict[str, str] | None]:
    """A lookup ``url -> credential payload`` for data URLs (see the module docstring)."""

    def lookup(url: str) -> dict[str, str] | None:
        parts = urlsplit(url)
        if parts.scheme != "s3":
            return None
        return store.credential(f"s3://{parts.netloc}") or store.credential("s3")

    return lookup


def check_task_credentials(spec: WorkflowSpec, store: Store) -> None:
    """Check that every credential the tasks of ``spec`` name exists with the keys they use.

    Raises:
        SubmitError: listing every problem at once, each with its fix.
    """
    missing: dict[str, list[str]] = {}
    problems: list[str] = []
    for task in spec.all_tasks():
        for name, use in task.credentials.items():
            payload = store.credential(name)
            if payload is None:
                missing.setdefault(name, []).append(task.name)
            else:
                problems += _use_problems(task, name, use, payload)
        problems += _env_clashes(task)
    reasons = [f"credential '{name}' (used by task {', '.join(repr(t) for t in tasks)}) "
               f"does not exist; store it with `osmo credential set {name} --payload "
               "KEY=VALUE ...`" for name, tasks in missing.items()]
    if reasons or problems:
        raise SubmitError("cannot use the credentials of this workflow:\n  "
                          + "\n  ".join(reasons + problems))


def _use_problems(task: TaskSpec, name: str, use: Any, payload: dict[str, str]) -> list[str]:
    keys = ", ".join(sorted(payload))
    if isinstance(use, str):
        return [f"task '{task.name}': credential '{name}' is mounted at {use} but its key "
                f"'{key}' {problem}; rename the key (`osmo credential set {name} ...`)"
                for key in payload if (problem := unusable_file_name(key))]
    return [f"task '{task.name}': credential '{name}' has no key '{key}' (for ${var}); "
            f"its keys: {keys}" for var, key in use.items() if key not in payload]


def _env_clashes(task: TaskSpec) -> list[str]:
    """Variables set twice: by two credentials, or by a credential and ``environment``."""
    setters: dict[str, list[str]] = {v: ["'environment'"] for v in task.environment}
    for name, use in task.credentials.items():
        for var in use if isinstance(use, dict) else ():
            setters.setdefault(var, []).append(f"credential '{name}'")
    return [f"task '{task.name}': ${var} is set by both {' and '.join(who)}; keep one"
            for var, who in setters.items() if len(who) > 1]


class CredentialHandlers:
    """Handlers for ``credential_*`` verbs."""

    def __init__(self, store: Store) -> None:
        self._store = store

    def set(self, request: dict[str, Any]) -> dict[str, Any]:
        """Store credential ``name`` with ``payload`` (a non-empty map of strings)."""
        name = _name(request)
        payload = str_map(request, "payload")
        if not payload:
            raise UsageError("a credential needs at least one --payload key=value")
        self._store.set_credential(name, payload, time.time())
        return {"name": name, "keys": sorted(payload)}

    def list(self, _request: dict[str, Any]) -> list[dict[str, Any]]:
        """Names and keys of stored credentials (never their values)."""
        return self._store.credentials()

    def delete(self, request: dict[str, Any]) -> dict[str, Any]:
        """Remove a credential."""
        name = _name(request)
        if not self._store.delete_credential(name):
            raise NotFoundError(f"no credential '{name}'")
        return {"name": name}


def _name(request: dict[str, Any]) -> str:
    """A credential name: a name, or ``s3://BUCKET`` for one bucket."""
    name: str = field(request, "name", str, max_len=_MAX_NAME)
    if not name or not set(name) <= _NAME_OK:
        raise UsageError(f"invalid credential name {shown(name)}: use letters, digits, -_.:/")
    return name
