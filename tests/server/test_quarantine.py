"""The quarantine's strike count: a task is quarantined the second time a server dies on it."""

from __future__ import annotations

import json
from pathlib import Path

from osmo.server.recovery import InFlight


def test_the_second_crash_on_a_task_quarantines_it(tmp_path: Path) -> None:
    applying = tmp_path / "applying.json"
    applying.write_text(json.dumps(["wf-1:boom:0", "wf-1:other:2"]))
    first = InFlight(applying)
    assert first.left == {"wf-1:boom:0", "wf-1:other:2"}
    assert first.strike(first.left) == set()  # first crash: both run again
    first.close()
    assert not applying.read_bytes()  # emptied for the new server

    applying.write_text(json.dumps(["wf-1:boom:1"]))  # boom's retry crashed it again
    second = InFlight(applying)
    assert second.strike(second.left) == {"wf-1:boom:1"}  # same task, any retry: quarantined
    second.close()
    assert json.loads((tmp_path / "crashes.json").read_text()) == {"wf-1:boom": 2,
                                                                   "wf-1:other": 1}
    assert (tmp_path / "crashes.json").stat().st_mode & 0o777 == 0o600


def test_nothing_left_writes_nothing(tmp_path: Path) -> None:
    inflight = InFlight(tmp_path / "applying.json")
    assert inflight.strike(inflight.left) == set()
    assert not (tmp_path / "crashes.json").exists()
    inflight.close()
