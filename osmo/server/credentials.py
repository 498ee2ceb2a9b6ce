"""Credentials: named secrets stored on the server, used to reach data URLs.

``osmo credential set NAME --payload key=value ...`` stores one; values never leave the
server through the API (``list`` shows names and keys only) and never reach logs. A data URL
picks its credential by name: for ``s3://BUCKET/...`` the credential called
``s3://BUCKET``, else the one called ``s3`` (keys: ``endpoint``, ``access_key``,
``secret_key``, ``region``, ``session_token``). ``file://`` URLs need none.

Credentials are stored in the state database (``OSMO_HOME/state.db``, readable only by the
server's user); tasks' own ``credentials:`` (injecting secrets into a task) are not
supported yet.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

from osmo.errors import NotFoundError, UsageError
from osmo.store.sqlite import Store

__all__ = ["CredentialApi", "url_credential"]

_NAME_OK = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789-_.:/")


def url_credential(store: Store) -> Callable[[str], dict[str, str] | None]:
    """A lookup ``url -> credential payload`` for data URLs (see the module docstring)."""

    def lookup(url: str) -> dict[str, str] | None:
        parts = urlsplit(url)
        if parts.scheme != "s3":
            return None
        return store.credential(f"s3://{parts.netloc}") or store.credential("s3")

    return lookup


class CredentialApi:
    """Handlers for ``credential_*`` verbs."""

    def __init__(self, store: Store) -> None:
        self._store = store

    def verbs(self) -> dict[str, Any]:
        """Verb name → handler."""
        return {"credential_set": self.set, "credential_list": self.list,
                "credential_delete": self.delete}

    def set(self, request: dict[str, Any]) -> dict[str, Any]:
        """Store credential ``name`` with ``payload`` (a non-empty map of strings)."""
        name = str(request.get("name") or "")
        payload = request.get("payload") or {}
        if not name or not set(name) <= _NAME_OK:
            raise UsageError(f"invalid credential name '{name}': use letters, digits, -_.:/")
        if not isinstance(payload, dict) or not payload:
            raise UsageError("a credential needs at least one --payload key=value")
        self._store.set_credential(name, {str(k): str(v) for k, v in payload.items()},
                                   time.time())
        return {"name": name, "keys": sorted(payload)}

    def list(self, _request: dict[str, Any]) -> list[dict[str, Any]]:
        """Names and keys of stored credentials (never their values)."""
        return self._store.credentials()

    def delete(self, request: dict[str, Any]) -> dict[str, Any]:
        """Remove a credential."""
        if not self._store.delete_credential(str(request["name"])):
            raise NotFoundError(f"no credential '{request['name']}'")
        return {"name": request["name"]}
