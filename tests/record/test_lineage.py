"""The Lineage record: dict, flat metadata-map and environment forms."""

from __future__ import annotations

import json
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from osmo.errors import OsmoError, UsageError
from osmo.record import Lineage, LineageInput


def full() -> Lineage:
    """A lineage with every field set."""
    return Lineage(
        workflow_id="wf-7", task="train", retry=2, attempt_id="att-9", node="node-a",
        command=("python", "train.py", "--lr", "0.1"), plugin=None,
        params={"lr": 0.1, "layers": [64, 64], "name": "é"}, image="osmo/learn:1",
        inputs=(LineageInput("data", "wf-7", "sha256:" + "a" * 64),),
        started_at=1700000000.25, ended_at=1700000123.5, exit_code=0,
        manifest_digest="sha256:" + "b" * 64, osmo_version="0.1.0",
    )


def test_dict_round_trip_is_json_safe() -> None:
    record = full()
    data = json.loads(json.dumps(record.to_dict()))
    assert data["command"] == ["python", "train.py", "--lr", "0.1"]
    assert data["inputs"] == [{"task": "data", "workflow_id": "wf-7", "manifest": "sha256:" + "a" * 64}]
    assert Lineage.from_dict(data) == record


def test_metadata_is_a_flat_string_map_that_round_trips() -> None:
    record = full()
    meta = record.to_metadata()
    assert all(isinstance(k, str) and isinstance(v, str) for k, v in meta.items())
    assert meta["workflow_id"] == "wf-7" and meta["task"] == "train"  # plain strings stay readable
    assert json.loads(meta["params"]) == record.params
    assert "plugin" not in meta  # None optional strings are omitted
    assert Lineage.from_metadata(meta) == record


def test_metadata_keeps_none_and_empty_string_apart() -> None:
    record = Lineage("wf", "t", attempt_id="", image=None, plugin="sim.rollout@1.2")
    back = Lineage.from_metadata(record.to_metadata())
    assert back.attempt_id == "" and back.image is None and back.plugin == "sim.rollout@1.2"


def test_metadata_ignores_unknown_keys_from_newer_writers() -> None:
    meta = full().to_metadata() | {"future_field": "x"}
    assert Lineage.from_metadata(meta) == full()


def test_defaults_make_a_partial_record() -> None:
    record = Lineage("wf", "t")
    assert record.retry == 0 and record.command is None and record.inputs == ()
    assert record.osmo_version  # stamped with the running osmo's version


@pytest.mark.parametrize(
    ("change", "needle"),
    [
        ({"task": None}, "task"),
        ({"retry": "1"}, "retry"),
        ({"retry": True}, "retry"),
        ({"command": "echo hi"}, "command"),
        ({"command": ["echo", 1]}, "command"),
        ({"inputs": [{"task": "a"}]}, "manifest"),
        ({"started_at": "yesterday"}, "started_at"),
        ({"params": [1, 2]}, "params"),
    ],
)
def test_from_dict_rejects_malformed_records(change: dict[str, Any], needle: str) -> None:
    data = full().to_dict() | change
    with pytest.raises(UsageError, match=needle):
        Lineage.from_dict(data)


def test_from_metadata_rejects_bad_json() -> None:
    meta = full().to_metadata() | {"params": "{not json"}
    with pytest.raises(UsageError, match="params"):
        Lineage.from_metadata(meta)


def test_from_env_reads_what_a_task_sees() -> None:
    env = {
        "OSMO_WORKFLOW_ID": "wf-3", "OSMO_TASK": "sim", "OSMO_RETRY": "1",
        "OSMO_ATTEMPT_ID": "att-1", "OSMO_NODE": "robot-2", "OSMO_PLUGIN": "sim.rollout@0.3",
        "OSMO_STARTED_AT": "1700000000.5", "OSMO_PARAMS": '{"episodes": 4}',
        "OSMO_INPUTS": '[{"task": "cfg", "workflow_id": "wf-3", "manifest": "sha256:00"}]',
    }
    record = Lineage.from_env(env)
    assert (record.workflow_id, record.task, record.retry) == ("wf-3", "sim", 1)
    assert record.attempt_id == "att-1" and record.node == "robot-2"
    assert record.plugin == "sim.rollout@0.3" and record.params == {"episodes": 4}
    assert record.inputs == (LineageInput("cfg", "wf-3", "sha256:00"),)
    assert record.started_at == 1700000000.5 and record.ended_at is None


def test_from_env_defaults_node_and_optional_fields(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("OSMO_ATTEMPT_ID", "OSMO_NODE", "OSMO_PARAMS", "OSMO_COMMAND"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("OSMO_WORKFLOW_ID", "wf-1")
    monkeypatch.setenv("OSMO_TASK", "t")
    monkeypatch.setenv("OSMO_RETRY", "0")
    record = Lineage.from_env()
    assert record.node and record.attempt_id is None and record.params == {}


@pytest.mark.parametrize(
    ("env", "needle"),
    [
        ({}, "OSMO_WORKFLOW_ID, OSMO_TASK, OSMO_RETRY not set"),
        ({"OSMO_WORKFLOW_ID": "w", "OSMO_TASK": "t"}, "OSMO_RETRY not set"),
        ({"OSMO_WORKFLOW_ID": "w", "OSMO_TASK": "t", "OSMO_RETRY": "x"}, "OSMO_RETRY"),
        ({"OSMO_WORKFLOW_ID": "w", "OSMO_TASK": "t", "OSMO_RETRY": "0",
          "OSMO_PARAMS": "{"}, "OSMO_PARAMS"),
    ],
)
def test_from_env_outside_a_task_says_what_is_missing(env: dict[str, str], needle: str) -> None:
    with pytest.raises(OsmoError, match=needle):
        Lineage.from_env(env)


_text = st.text(max_size=20)
_json_leaf = st.none() | st.booleans() | st.integers(-(2**40), 2**40) | _text | st.floats(
    allow_nan=False, allow_infinity=False)
_params = st.dictionaries(_text, st.recursive(
    _json_leaf, lambda inner: st.lists(inner, max_size=3) | st.dictionaries(_text, inner, max_size=3),
    max_leaves=8), max_size=4)


@given(
    workflow_id=_text, task=_text, retry=st.integers(0, 100),
    attempt_id=st.none() | _text, node=_text,
    command=st.none() | st.lists(_text, max_size=4).map(tuple),
    image=st.none() | _text, params=_params,
    started_at=st.none() | st.floats(0, 4e9),
    exit_code=st.none() | st.integers(-255, 255),
)
def test_metadata_round_trip_property(
    workflow_id: str, task: str, retry: int, attempt_id: str | None, node: str,
    command: tuple[str, ...] | None, image: str | None, params: dict[str, Any],
    started_at: float | None, exit_code: int | None,
) -> None:
    record = Lineage(workflow_id, task, retry, attempt_id=attempt_id, node=node, command=command,
                     image=image, params=params, started_at=started_at, exit_code=exit_code)
    assert Lineage.from_metadata(record.to_metadata()) == record
    assert Lineage.from_dict(json.loads(json.dumps(record.to_dict()))) == record
