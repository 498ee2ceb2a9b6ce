"""The task rows the store writes: ``(workflow id, name, status, state JSON)``.

The state JSON is exactly ``json.dumps(state.to_dict())``. A submit writes a row per task
(100,000 for a big fan-out) whose states differ mostly in their names, so :func:`task_rows`
encodes what follows the names once per distinct value and joins it to each task's own
``workflow_id``, ``name`` and ``group``: the same text, at a fraction of the cost. Pure: no
database access.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from json.encoder import encode_basestring_ascii  # what json.dumps encodes strings with
from operator import attrgetter
from typing import Any

from osmo.scheduler.state import TaskState

__all__ = ["task_rows"]

_HEAD = ("workflow_id", "name", "group")
_TAIL = tuple(f for f in TaskState.__dataclass_fields__ if f not in _HEAD)
_tail_of = attrgetter(*_TAIL)
_STATUS = _TAIL.index("status")


def task_rows(states: Iterable[TaskState]) -> list[tuple[str, str, str, str]]:
    """``(workflow_id, name, status name, json.dumps(state.to_dict()))`` of each state."""
    tails: dict[tuple[Any, ...], str] = {}
    rows = []
    for state in states:
        values = _tail_of(state)
        # types too: 0 == 0.0 == False, but json.dumps writes each its own way
        key = (values, tuple(map(type, values)))
        tail = tails.get(key)
        if tail is None:
            data = dict(zip(_TAIL, values, strict=True))
            data["status"] = values[_STATUS].name
            tail = tails[key] = ", " + json.dumps(data)[1:]
        rows.append((state.workflow_id, state.name, values[_STATUS].name,
                     f'{{"workflow_id": {encode_basestring_ascii(state.workflow_id)}, '
                     f'"name": {encode_basestring_ascii(state.name)}, '
                     f'"group": {encode_basestring_ascii(state.group)}{tail}'))
    return rows
