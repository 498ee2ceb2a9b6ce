"""A task's ``credentials:``: which secret values it gets, as environment variables or files.

A task names stored credentials (``osmo credential set``) in two forms:

- ``NAME: {ENV: key}`` — environment variable ``ENV`` gets the value of ``key`` in
  credential ``NAME``;
- ``NAME: /path`` — every key of credential ``NAME`` becomes a file ``/path/<key>`` holding
  its value (mode 0600), mapped to the attempt's private folder like ``files:`` paths
  (``osmo.worker.workdir``).

The worker receives the payloads of the credentials a task names (``Secrets``: credential
name → payload) from the server: the local pool looks them up in the store when the attempt
is prepared; a remote worker gets them with its assignment. A credential deleted after the
workflow was submitted fails the attempt's start with a :class:`SecretError`.

This module never logs, stores or reports a secret value; error messages name credentials
and keys only.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from osmo.errors import OsmoError
from osmo.spec.model import TaskSpec

__all__ = ["SecretError", "SecretLookup", "Secrets", "gather", "mounts",
           "secret_env", "secret_values", "unusable_file_name"]

Secrets = Mapping[str, Mapping[str, str]]
"""Credential name → payload (key → secret value)."""

SecretLookup = Callable[[str], Mapping[str, str] | None]
"""Credential name → payload, or None when there is no such credential."""

_FIX = "store it again with `osmo credential set {name} --payload KEY=VALUE ...`"


class SecretError(OsmoError):
    """A credential a task names is missing or lacks a key (the message says which)."""


def gather(task: TaskSpec, lookup: SecretLookup | None) -> dict[str, Mapping[str, str]]:
    """Look up the payload of every credential ``task`` names.

    Raises:
        SecretError: a credential does not exist (any more), or there is no lookup.
    """
    found: dict[str, Mapping[str, str]] = {}
    for name in task.credentials:
        payload = lookup(name) if lookup is not None else None
        if payload is None:
            raise SecretError(f"task '{task.name}': credential '{name}' does not exist (deleted "
                              f"after the workflow was submitted?); {_FIX.format(name=name)}")
        found[name] = payload
    return found


def _payload(task: TaskSpec, secrets: Secrets, name: str) -> Mapping[str, str]:
    payload = secrets.get(name)
    if payload is None:
        raise SecretError(f"task '{task.name}': credential '{name}' was not given to this "
                          f"worker; {_FIX.format(name=name)}")
    return payload


def secret_env(task: TaskSpec, secrets: Secrets) -> dict[str, str]:
    """The environment variables ``task``'s ``NAME: {ENV: key}`` credentials set.

    Raises:
        SecretError: a credential is missing from ``secrets`` or lacks a named key.
    """
    env: dict[str, str] = {}
    for name, use in task.credentials.items():
        if not isinstance(use, Mapping):
            continue
        payload = _payload(task, secrets, name)
        for var, key in use.items():
            if key not in payload:
                raise SecretError(f"task '{task.name}': credential '{name}' has no key '{key}' "
                                  f"(for ${var}); its keys: {', '.join(sorted(payload))}")
            env[str(var)] = payload[key]
    return env


def mounts(task: TaskSpec, secrets: Secrets) -> dict[str, Mapping[str, str]]:
    """Mount path → payload (file name → contents) of ``task``'s ``NAME: /path`` credentials.

    Raises:
        SecretError: a credential is missing from ``secrets``, or a key cannot be a file name.
    """
    out: dict[str, Mapping[str, str]] = {}
    for name, use in task.credentials.items():
        if isinstance(use, str):
            payload = _payload(task, secrets, name)
            for key in payload:
                problem = unusable_file_name(key)
                if problem:
                    raise SecretError(f"task '{task.name}': credential '{name}' is mounted at "
                                      f"{use} but its key '{key}' {problem}; rename the key")
            out[use] = payload
    return out


def secret_values(task: TaskSpec, secrets: Secrets) -> list[str]:
    """Every value of every credential ``task`` names (what its logs must mask)."""
    return [value for name in task.credentials for value in secrets.get(name, {}).values()]


def unusable_file_name(key: str) -> str | None:
    """Why ``key`` cannot name a file in a mount folder, or None when it can."""
    if key in ("", ".", ".."):
        return "is not a file name"
    if "/" in key or "\0" in key:
        return "contains '/' or a NUL character"
    return None
