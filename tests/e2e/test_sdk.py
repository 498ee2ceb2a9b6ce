"""The Python SDK end to end: builder → Client.submit → wait → logs, against a real server."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

import osmo
from tests.conftest import Osmo


def test_builder_submit_wait_and_logs(shared_osmo: Osmo) -> None:
    wf = osmo.Workflow("sdk-chain")
    wf.task("make", ["sh", "-c", "echo 20 > {{output}}/n; echo made"])
    wf.task("double", ["sh", "-c", "echo $(( $(cat {{input:make}}/n) * 2 ))"], inputs=["make"])
    with osmo.Client(home=shared_osmo.home) as client:
        wf_id = client.submit(wf)
        result = client.wait(wf_id, timeout=120)
        assert result.ok and result.status is osmo.WorkflowStatus.COMPLETED
        assert [t.name for t in result.tasks] == ["make", "double"]
        assert all(t.exit_code == 0 and t.duration is not None for t in result.tasks)
        texts = [r.text for r in client.logs(wf_id, task="double") if r.stream == "stdout"]
        assert texts == ["40"]
        assert wf_id in [w.id for w in client.list(name="sdk-chain")]


def test_wait_sees_the_end_at_once_and_shows_updates_at_most_every_interval(
        shared_osmo: Osmo) -> None:
    """``min_interval`` spaces the reads, never the end: the server's notice of a workflow's
    end cuts the pause short, and the final state is read (and shown) at once."""
    wf = osmo.Workflow("sdk-wait")
    wf.task("first", ["sleep", "0.4"])
    wf.task("second", ["sleep", "0.4"], inputs=["first"])
    shown: list[tuple[float, osmo.WorkflowInfo]] = []
    with osmo.Client(home=shared_osmo.home) as client:
        wf_id = client.submit(wf)
        started = time.monotonic()
        result = client.wait(wf_id, timeout=120, min_interval=30,
                             on_update=lambda i: shown.append((time.monotonic(), i)))
        waited = time.monotonic() - started
    assert result.status is osmo.WorkflowStatus.COMPLETED
    assert waited < 30, "the end waited out the update interval"
    assert len(shown) == 2, [i.status for _, i in shown]  # the first read, then the end
    assert shown[0][1].status is not osmo.WorkflowStatus.COMPLETED
    assert shown[-1][1].status is osmo.WorkflowStatus.COMPLETED
    assert [t.status for t in shown[-1][1].tasks] == [osmo.TaskStatus.COMPLETED] * 2


def test_wait_reads_a_workflow_no_more_often_than_its_reads_cost(
        shared_osmo: Osmo, monkeypatch: pytest.MonkeyPatch) -> None:
    """Full reads for ``on_update`` (a large workflow's cost the server most) are spaced by
    nine times what the last one took: with each read taking 0.2 s, a workflow that sends
    a notice every few milliseconds is read about once a second, and its end is shown."""
    wf = osmo.Workflow("sdk-wait-cost")
    previous = None
    for index in range(30):
        wf.task(f"t{index}", ["sleep", "0.15"], inputs=[previous] if previous else [])
        previous = f"t{index}"
    shown: list[float] = []
    with osmo.Client(home=shared_osmo.home) as client:
        real_get = client.get

        def slow_get(workflow_id: str, **kwargs: object) -> osmo.WorkflowInfo:
            time.sleep(0.2)
            return real_get(workflow_id, **kwargs)  # type: ignore[arg-type]

        monkeypatch.setattr(client, "get", slow_get)
        wf_id = client.submit(wf)
        started = time.monotonic()
        result = client.wait(wf_id, timeout=120, min_interval=0,
                             on_update=lambda i: shown.append(time.monotonic()))
        waited = time.monotonic() - started
    assert result.status is osmo.WorkflowStatus.COMPLETED
    gaps = [b - a for a, b in zip(shown[:-2], shown[1:-1], strict=True)]  # the end: at once
    assert waited > 4 and all(gap >= 0.2 * 9 for gap in gaps), (gaps, waited)
    assert len(shown) <= waited / (0.2 * 10) + 2, (len(shown), waited)


def test_submit_dict_and_failure_result(shared_osmo: Osmo) -> None:
    spec = {"workflow": {"name": "sdk-dict", "tasks": [
        {"name": "bad", "command": ["sh", "-c", "echo oops >&2; exit 5"]}]}}
    with osmo.Client(home=shared_osmo.home) as client:
        result = client.wait(client.submit(spec), timeout=120)
        assert not result.ok and result.status is osmo.WorkflowStatus.FAILED
        assert result.task("bad").exit_code == 5
        assert result.task("bad").status is osmo.TaskStatus.FAILED


def test_invalid_builder_raises_spec_error(shared_osmo: Osmo) -> None:
    wf = osmo.Workflow("sdk-bad")
    wf.task("a", ["true"], inputs=["missing"])
    with osmo.Client(home=shared_osmo.home) as client, pytest.raises(osmo.SpecError) as err:
        client.submit(wf)
    assert "missing" in str(err.value)
    assert isinstance(err.value, osmo.OsmoError)


def test_unknown_workflow_is_not_found(shared_osmo: Osmo) -> None:
    with osmo.Client(home=shared_osmo.home) as client, pytest.raises(osmo.NotFoundError):
        client.get("nothing-1")


# The public API, exactly (httpx's tests/test_exported_members.py does the same): adding or
# dropping a public name is a decision, made here as well as in osmo/__init__.py.
CURATED = [
    "Client", "Diagnostic", "InfrastructureError", "LogRecord", "NotFoundError", "OsmoError",
    "Param", "ServerUnreachable", "SpecError", "SubmitError", "TaskContext", "TaskInfo",
    "TaskStatus", "UsageError", "Workflow", "WorkflowFailed", "WorkflowInfo", "WorkflowSpec",
    "WorkflowStatus", "load_spec", "task_type",
]


def test_public_api_is_curated() -> None:
    assert osmo.__all__ == CURATED  # the exact set, kept sorted
    assert dir(osmo) == sorted(CURATED)
    for name in CURATED:
        value = getattr(osmo, name)
        assert value.__module__.startswith("osmo."), (name, value.__module__)
        assert value.__name__ == name  # the real object, not an alias
    with pytest.raises(AttributeError):
        osmo.Scheduler  # noqa: B018 - a private module's name is not reachable lazily
    errors = [getattr(osmo, n) for n in CURATED
              if isinstance(getattr(osmo, n), type) and issubclass(getattr(osmo, n), Exception)]
    assert {e.__name__ for e in errors} == {
        "InfrastructureError", "NotFoundError", "OsmoError", "ServerUnreachable", "SpecError",
        "SubmitError", "UsageError", "WorkflowFailed"}
    assert all(issubclass(e, osmo.OsmoError) for e in errors)


def test_import_osmo_is_light() -> None:
    import subprocess
    import sys

    code = ("import sys, osmo; heavy = [m for m in ('zenoh', 'rich', 'jinja2', 'sqlite3', "
            "'mujoco', 'torch', 'lerobot') if m in sys.modules]; print(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=Path(__file__).parents[2]).stdout.strip()
    assert out == "[]"
