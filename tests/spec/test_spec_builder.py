"""The Python builder: examples, errors, and round-trip properties over generated workflows."""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from osmo.errors import SpecError
from osmo.spec import (
    ExitAction,
    InputSpec,
    ResourceSpec,
    Task,
    Workflow,
    WorkflowSpec,
    dump_yaml,
    load_spec,
    spec_from_dict,
    spec_to_dict,
)


def test_bare_tasks_example() -> None:
    wf = Workflow("train-eval", pool="local", exec_timeout="2h", max_retries=1,
                  labels={"team": "rl"})
    wf.resource(cpu=4, memory="8Gi").resource("gpu", gpu=1)
    wf.task("prep", ["python", "prep.py"], environment={"SEED": 1, "FAST": True})
    wf.task("train", "python train.py --data {{input:0}}", inputs=["prep"], resource="gpu",
            exit_actions={"RESCHEDULE": "3", "complete": [0]}, cache=False)
    spec = wf.build()
    assert spec.bare_tasks and spec.pool == "local" and spec.max_retries == 1
    assert spec.timeout.exec_timeout == 7200
    assert spec.resources["default"] == ResourceSpec(cpu=4, memory=8 * 2**30)
    assert spec.task("prep").environment == {"SEED": "1", "FAST": "true"}
    train = spec.task("train")
    assert train.command == ("python", "train.py", "--data", "{{input:0}}")
    assert train.upstream_tasks() == ("prep",)
    assert train.exit_action(3) is ExitAction.RESCHEDULE and not train.cache
    assert load_spec(text=wf.to_yaml()) == spec


def test_group_example() -> None:
    wf = Workflow("sim")
    wf.group("rollout", [Task("server", ["sim-server"], lead=True),
                         Task("client", ["sim-client", "{{host:server}}"],
                              files={"/tmp/cfg": "a: 1", "/tmp/raw": b"\x00\xff"})],
             barrier=False, ignore_nonlead_status=False)
    wf.group("score", [Task("eval", ["eval"], inputs=["client", InputSpec(task="x",
                                                                          workflow="old-1")])])
    spec = wf.build()
    assert not spec.bare_tasks
    rollout = spec.groups[0]
    assert rollout.lead.name == "server" and not rollout.barrier
    assert not rollout.ignore_nonlead_status
    raw = {f.path: f for f in spec.task("client").files}["/tmp/raw"]
    assert raw.base64 and raw.contents == "AP8="
    assert spec.task("eval").inputs[1] == InputSpec(task="x", workflow="old-1")


def test_builder_errors_use_the_same_rules() -> None:
    wf = Workflow("bad name!").task("a", ["echo"], inputs=["b"])
    wf.group("g", [Task("b", ["echo"])])
    with pytest.raises(SpecError) as info:
        wf.build()
    messages = [d.message for d in info.value.diagnostics]
    assert any("workflow name 'bad name!' is not a valid name" in m for m in messages)
    assert any("both 'tasks' and 'groups'" in m for m in messages)
    assert all(d.file == "<builder>" for d in info.value.diagnostics)


def test_empty_builder_is_an_error() -> None:
    with pytest.raises(SpecError, match=r"'workflow\.tasks' is empty"):
        Workflow("x").build()


def test_jinja_like_text_survives_round_trip() -> None:
    wf = Workflow("x").task("a", ["echo", "{{ not_a_var }}", "{% raw %}", "{#", "{{output}}"])
    spec = wf.build()
    assert spec.task("a").command[1:] == ("{{ not_a_var }}", "{% raw %}", "{#", "{{output}}")
    assert load_spec(text=dump_yaml(spec)) == spec
    assert load_spec(text=wf.to_yaml()) == spec


# --- properties -------------------------------------------------------------------------

NAMES = st.from_regex(r"[a-z][a-z0-9_-]{0,8}[a-z0-9]", fullmatch=True)
TEXT = st.text(st.characters(blacklist_categories=("Cs",)), max_size=20)
WORDS = st.lists(TEXT, min_size=1, max_size=3)
# environment values never hold NUL: the spec refuses them (no process can be given one)
ENV_TEXT = st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\0"),
                   max_size=20)
TOKENS = st.sampled_from(["{{output}}", "{{ workflow_id }}", "{{uuid}}"])


def _key(name: str) -> str:
    return name.lower().replace("_", "-")


@st.composite
def exit_actions(draw: st.DrawFn) -> dict[str, str]:
    points = sorted(draw(st.lists(st.integers(0, 300), unique=True, max_size=6)))
    ranges = [f"{points[i]}-{points[i + 1]}" for i in range(0, len(points) - 1, 2)]
    actions = draw(st.permutations(["COMPLETE", "FAIL", "RESCHEDULE"]))
    out: dict[str, list[str]] = {}
    for i, r in enumerate(ranges):
        out.setdefault(actions[i % 3], []).append(r)
    return {k: ",".join(v) for k, v in out.items()}


@st.composite
def task_kwargs(draw: st.DrawFn, upstream: list[str], with_resources: bool) -> dict[str, Any]:
    inputs = draw(st.lists(st.sampled_from(upstream), unique=True, max_size=3)) if upstream else []
    command = [*draw(WORDS), draw(TOKENS)]
    if inputs:
        command.append(f"{{{{input:{draw(st.integers(0, len(inputs) - 1))}}}}}")
    env_keys = st.from_regex(r"[A-Z_][A-Z0-9_]{0,6}", fullmatch=True)
    files = draw(st.dictionaries(st.from_regex(r"/tmp/[a-z]{1,6}", fullmatch=True),
                                 TEXT | st.binary(max_size=10), max_size=2))
    return {
        "command": command,
        "args": draw(st.lists(TEXT, max_size=2)),
        "image": draw(st.none() | st.just("python:3.11")),
        "environment": draw(st.dictionaries(env_keys, ENV_TEXT | st.integers() | st.booleans(),
                                            max_size=3)),
        "files": files,
        "inputs": inputs,
        "resource": "default" if with_resources and draw(st.booleans()) else None,
        "exit_actions": draw(exit_actions()),
        "cache": draw(st.booleans()),
    }


@st.composite
def workflows(draw: st.DrawFn) -> Workflow:
    names = draw(st.lists(NAMES, min_size=2, max_size=8, unique_by=_key))
    wf = Workflow(
        draw(NAMES),
        pool=draw(st.none() | NAMES),
        labels=draw(st.dictionaries(NAMES, NAMES, max_size=3)),
        exec_timeout=draw(st.none() | st.integers(1, 10**6) | st.sampled_from(["30m", "2h"])),
        queue_timeout=draw(st.none() | st.integers(1, 10**6)),
        max_retries=draw(st.none() | st.integers(0, 5)),
    )
    with_resources = draw(st.booleans())
    if with_resources:
        wf.resource(cpu=draw(st.none() | st.integers(0, 64)),
                    memory=draw(st.none() | st.integers(0, 2**40) | st.just("512Mi")))
    if draw(st.booleans()):
        for i, name in enumerate(names):
            wf.task(name, **draw(task_kwargs(names[:i], with_resources)))
        return wf
    group_names, done = names[::3], []
    task_names = [n for n in names if n not in group_names] or ["solo"]
    cut = sorted(set(draw(st.lists(st.integers(1, len(task_names)), max_size=3))))
    bounds = zip([0, *cut], [*cut, len(task_names)], strict=True)
    chunks = [task_names[a:b] for a, b in bounds if a < b]
    for g, chunk in enumerate(chunks):
        lead = draw(st.integers(0, len(chunk) - 1))
        tasks = [Task(n, lead=len(chunk) > 1 and i == lead,
                      **draw(task_kwargs(list(done), with_resources)))
                 for i, n in enumerate(chunk)]
        wf.group(group_names[g] if g < len(group_names) else f"group{g}z", tasks,
                 barrier=draw(st.booleans()), ignore_nonlead_status=draw(st.booleans()))
        done.extend(chunk)
    return wf


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(workflows())
def test_builder_round_trips(wf: Workflow) -> None:
    spec = wf.build()
    assert isinstance(spec, WorkflowSpec)
    assert load_spec(text=dump_yaml(spec)) == spec
    assert load_spec(text=wf.to_yaml()) == spec
    assert spec_from_dict(spec_to_dict(spec)) == spec
    dumped = dump_yaml(spec)
    assert load_spec(text=dump_yaml(load_spec(text=dumped))) == spec
