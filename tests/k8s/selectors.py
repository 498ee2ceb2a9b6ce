"""Label and field selectors as the API server parses them (``labelSelector``, ``fieldSelector``).

Labels: ``k``, ``!k``, ``k=v``, ``k==v``, ``k!=v``, ``k in (a,b)``, ``k notin (a,b)``, joined by
commas. Fields: ``path=v``, ``path==v``, ``path!=v`` over the few fields each kind allows
(``FIELDS``). A selector that does not parse raises :class:`SelectorError` (the server answers
400 BadRequest with its message).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["FIELDS", "SelectorError", "field_selector", "label_selector"]

Predicate = Callable[[dict[str, Any]], bool]

FIELDS: Mapping[str, frozenset[str]] = {
    "Pod": frozenset({"spec.nodeName", "spec.restartPolicy", "spec.schedulerName",
                      "spec.serviceAccountName", "status.phase", "status.podIP",
                      "status.nominatedNodeName"}),
    "Secret": frozenset({"type"}),
}
"""Fields a kind may be selected by, besides ``metadata.name`` and ``metadata.namespace``."""

_REQUIREMENT = re.compile(
    r"\s*(?:(?P<not>!)\s*(?P<nkey>[^\s,=!()]+)"
    r"|(?P<key>[^\s,=!()]+)\s*(?:(?P<op>==|=|!=)\s*(?P<value>[^\s,=!()]*)"
    r"|\s(?P<setop>in|notin)\s*\((?P<values>[^()]*)\))?)\s*(?:,|$)")


class SelectorError(ValueError):
    """A selector that does not parse."""


def label_selector(text: str | None) -> Predicate:
    """A predicate on objects for a label selector (None or empty: everything)."""
    checks: list[Callable[[Mapping[str, str]], bool]] = []
    pos, text = 0, (text or "").strip()
    while pos < len(text):
        match = _REQUIREMENT.match(text, pos)
        if match is None or match.end() == pos:
            raise SelectorError(f"unable to parse requirement: {text[pos:]!r}")
        checks.append(_label_check(match))
        pos = match.end()

    def test(obj: dict[str, Any]) -> bool:
        labels = (obj.get("metadata") or {}).get("labels") or {}
        return all(check(labels) for check in checks)
    return test


def _label_check(match: re.Match[str]) -> Callable[[Mapping[str, str]], bool]:
    if match["not"]:
        key = match["nkey"]
        return lambda labels: key not in labels
    key, op = match["key"], match["op"] or match["setop"]
    if op is None:
        return lambda labels: key in labels
    if op in ("=", "=="):
        value = match["value"]
        return lambda labels: labels.get(key) == value
    if op == "!=":
        value = match["value"]
        return lambda labels: labels.get(key) != value
    values = {v.strip() for v in match["values"].split(",") if v.strip()}
    if op == "in":
        return lambda labels: labels.get(key) in values
    return lambda labels: labels.get(key) not in values


def field_selector(text: str | None, kind: str) -> Predicate:
    """A predicate on objects of ``kind`` for a field selector (None or empty: everything)."""
    allowed = FIELDS.get(kind, frozenset()) | {"metadata.name", "metadata.namespace"}
    checks: list[Predicate] = []
    for part in filter(None, (p.strip() for p in (text or "").split(","))):
        match = re.fullmatch(r"([A-Za-z.]+)\s*(==|=|!=)\s*(.*)", part)
        if match is None:
            raise SelectorError(f"invalid selector: {part!r}; can't understand {part!r}")
        path, op, value = match.groups()
        if path not in allowed:
            raise SelectorError(f'"{path}" is not a known field selector: only '
                                + ", ".join(f'"{f}"' for f in sorted(allowed)))
        checks.append(_field_check(path.split("."), op == "!=", value))
    return lambda obj: all(check(obj) for check in checks)


def _field_check(path: list[str], negate: bool, value: str) -> Predicate:
    def test(obj: dict[str, Any]) -> bool:
        found: Any = obj
        for key in path:
            found = found.get(key) if isinstance(found, dict) else None
        return (str(found or "") == value) != negate
    return test
