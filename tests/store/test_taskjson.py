"""Task rows are written as ``json.dumps(state.to_dict())`` would write them, byte for byte."""

from __future__ import annotations

import json

from hypothesis import given, settings
from hypothesis import strategies as st

from osmo.scheduler.state import TaskState
from osmo.status import TaskStatus
from osmo.store.taskjson import task_rows

TEXT = st.text(alphabet=st.characters(codec=None), max_size=12)  # surrogates, quotes, é
NUMBER = st.one_of(st.none(), st.integers(-3, 3), st.floats(allow_nan=False), st.booleans())

STATES = st.builds(
    TaskState, workflow_id=TEXT, name=TEXT, group=TEXT, status=st.sampled_from(TaskStatus),
    retry=st.integers(0, 3), attempt_id=st.one_of(st.none(), TEXT),
    node_id=st.one_of(st.none(), TEXT), exit_code=NUMBER, output=st.one_of(st.none(), TEXT),
    message=TEXT, reused=st.booleans(), created_at=NUMBER, ended_at=NUMBER)


@settings(max_examples=300, deadline=None)
@given(st.lists(STATES, max_size=6), st.lists(st.integers(0, 5), max_size=6))
def test_each_row_is_the_json_of_its_state(states: list[TaskState], repeats: list[int]) -> None:
    # states alike but for the name share their encoded tail: repeat some under new names
    states += [TaskState(**{**vars(states[i]), "name": f"copy{n}"})
               for n, i in enumerate(repeats) if i < len(states)]
    rows = task_rows(states)
    assert [r[:3] for r in rows] == [(s.workflow_id, s.name, s.status.name) for s in states]
    assert [r[3] for r in rows] == [json.dumps(s.to_dict()) for s in states]


def test_equal_numbers_of_other_types_are_written_each_its_own_way() -> None:
    states = [TaskState("w", "a", "a", created_at=0.0, exit_code=1),
              TaskState("w", "b", "b", created_at=0, exit_code=True)]
    rows = task_rows(states)
    assert '"created_at": 0.0' in rows[0][3] and '"exit_code": 1' in rows[0][3]
    assert '"created_at": 0,' in rows[1][3] and '"exit_code": true' in rows[1][3]
