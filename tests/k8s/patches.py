"""The PATCH bodies the API server accepts: JSON merge patch and JSON patch.

``application/merge-patch+json`` is RFC 7386. ``application/strategic-merge-patch+json``
(the real client's default for a dict body) is applied the same way: lists are replaced
whole; ``$patch`` directives and merge keys are not understood. ``application/json-patch+json``
is RFC 6902 (add, remove, replace, test, copy, move). Anything else is 415.
"""

from __future__ import annotations

import copy
from typing import Any

from tests.k8s.store import ApiError

__all__ = ["MERGE_TYPES", "apply_patch"]

MERGE_TYPES = ("application/merge-patch+json", "application/strategic-merge-patch+json")
JSON_PATCH = "application/json-patch+json"


def apply_patch(obj: dict[str, Any], patch: Any, content_type: str) -> dict[str, Any]:
    """``obj`` with ``patch`` applied (a new object); ApiError 415/422 when it cannot be."""
    kind = content_type.split(";")[0].strip()
    if kind in MERGE_TYPES:
        if not isinstance(patch, dict):
            raise ApiError(400, "BadRequest", "a merge patch must be a JSON object")
        merged = _merge(copy.deepcopy(obj), patch)
        assert isinstance(merged, dict)
        return merged
    if kind == JSON_PATCH:
        if not isinstance(patch, list):
            raise ApiError(400, "BadRequest", "a JSON patch must be a list of operations")
        out = copy.deepcopy(obj)
        for op in patch:
            out = _operation(out, op)
        return out
    raise ApiError(415, "UnsupportedMediaType",
                   f"the body of the request was in an unknown format - accepted media types "
                   f"include: {JSON_PATCH}, {', '.join(MERGE_TYPES)}")


def _merge(target: Any, patch: Any) -> Any:
    if not isinstance(patch, dict):
        return copy.deepcopy(patch)
    if not isinstance(target, dict):
        target = {}
    for key, value in patch.items():
        if value is None:
            target.pop(key, None)
        else:
            target[key] = _merge(target.get(key), value)
    return target


def _pointer(path: str) -> list[str]:
    if path == "":
        return []
    if not path.startswith("/"):
        raise ApiError(422, "Invalid", f"invalid JSON pointer {path!r}")
    return [p.replace("~1", "/").replace("~0", "~") for p in path[1:].split("/")]


def _operation(doc: dict[str, Any], op: Any) -> dict[str, Any]:
    if not isinstance(op, dict) or "op" not in op or "path" not in op:
        raise ApiError(400, "BadRequest", f"invalid JSON patch operation {op!r}")
    name, parts = op["op"], _pointer(op["path"])
    if name in ("copy", "move"):
        value = _get(doc, _pointer(op.get("from", "")))
        if name == "move":
            _remove(doc, _pointer(op["from"]))
        _add(doc, parts, copy.deepcopy(value))
    elif name == "add":
        _add(doc, parts, copy.deepcopy(op.get("value")))
    elif name == "remove":
        _remove(doc, parts)
    elif name == "replace":
        _remove(doc, parts)
        _add(doc, parts, copy.deepcopy(op.get("value")))
    elif name == "test":
        if _get(doc, parts) != op.get("value"):
            raise ApiError(422, "Invalid", f"testing value {op['path']} failed")
    else:
        raise ApiError(400, "BadRequest", f"unknown JSON patch operation {name!r}")
    return doc


def _parent(doc: Any, parts: list[str]) -> Any:
    if not parts:
        raise ApiError(422, "Invalid", "a JSON patch may not replace the whole object")
    return _get(doc, parts[:-1])


def _get(doc: Any, parts: list[str]) -> Any:
    for part in parts:
        try:
            doc = doc[int(part)] if isinstance(doc, list) else doc[part]
        except (KeyError, IndexError, ValueError, TypeError):
            raise ApiError(422, "Invalid", f"path /{'/'.join(parts)} does not exist") from None
    return doc


def _add(doc: Any, parts: list[str], value: Any) -> None:
    parent, last = _parent(doc, parts), parts[-1]
    if isinstance(parent, list):
        parent.insert(len(parent) if last == "-" else int(last), value)
    elif isinstance(parent, dict):
        parent[last] = value
    else:
        raise ApiError(422, "Invalid", f"cannot add at /{'/'.join(parts)}")


def _remove(doc: Any, parts: list[str]) -> None:
    parent, last = _parent(doc, parts), parts[-1]
    _get(doc, parts)  # 422 when absent
    if isinstance(parent, list):
        del parent[int(last)]
    else:
        del parent[last]
