"""Loading valid specs: every field lands in the model with normalised values."""

from __future__ import annotations

import base64
from pathlib import Path

import pytest

from osmo.errors import SpecError
from osmo.spec import (
    ExitAction,
    ExitRule,
    FileSpec,
    InputSpec,
    ResourceSpec,
    Timeouts,
    TopologySpec,
    dump_yaml,
    load_spec,
    spec_from_dict,
    spec_to_dict,
)

VALID = Path(__file__).parent / "valid"
GI = 2**30


@pytest.fixture(scope="module")
def full():  # type: ignore[no-untyped-def]
    return load_spec(VALID / "full.yaml")


def test_workflow_fields(full) -> None:  # type: ignore[no-untyped-def]
    assert full.name == "full-example"
    assert full.pool == "local"
    assert full.labels == {"team": "robotics", "run": "7"}
    assert full.max_retries == 2
    assert full.timeout == Timeouts(exec_timeout=7200, queue_timeout=90)
    assert not full.bare_tasks
    assert [g.name for g in full.groups] == ["prep", "sim"]


def test_resources(full) -> None:  # type: ignore[no-untyped-def]
    assert full.resources["default"] == ResourceSpec(
        cpu=4, gpu=0, memory=8 * GI, storage=int(1.5 * 2**40), platform="x86",
        nodes_excluded=("node-a",),
        topology=(TopologySpec("rack", "g1", "preferred"),))
    assert full.resources["small"] == ResourceSpec(cpu=1, memory=512 * 2**20)
    assert full.resources["small-gpu"] == ResourceSpec(cpu=1, gpu=1, memory=512 * 2**20)
    assert full.resource_for(full.task("client")) == full.resources["small"]
    assert full.resource_for(full.task("generate")) == full.resources["default"]
    assert full.resources["default"].pos is not None
    assert full.resources["default"].pos.line == 15


def test_task_fields(full) -> None:  # type: ignore[no-untyped-def]
    gen = full.task("generate")
    assert gen.image == "python:3.11"
    assert gen.command == ("python", "gen.py")
    assert gen.args == ("--out", "{{output}}", "--id", "{{ workflow_id }}")
    assert gen.environment == {"SEED": "42", "DEBUG": "true", "RATE": "1.50", "NAME": "gen"}
    assert gen.credentials == {"s3": {"AWS_ACCESS_KEY_ID": "key_id"}, "ssh": "/root/.ssh"}
    assert gen.cache is False
    assert gen.resource == "default"
    assert gen.pos is not None and (gen.pos.line, gen.pos.col) == (32, 7)


def test_files(full) -> None:  # type: ignore[no-untyped-def]
    files = {f.path: f for f in full.task("generate").files}
    assert files["/tmp/hello.txt"] == FileSpec("/tmp/hello.txt", "hello from a local file\n")
    blob = files["/tmp/blob.bin"]
    assert blob.base64 and base64.b64decode(blob.contents) == (VALID / "data/blob.bin").read_bytes()
    assert files["/tmp/inline.sh"].contents == "echo {{output}}\n"
    assert files["/tmp/encoded"] == FileSpec("/tmp/encoded", "aGVsbG8=", base64=True)


def test_exit_actions(full) -> None:  # type: ignore[no-untyped-def]
    gen = full.task("generate")
    assert gen.exit_actions == (
        ExitRule(ExitAction.COMPLETE, ((0, 0),)),
        ExitRule(ExitAction.RESCHEDULE, ((3, 3), (10, 20))),
        ExitRule(ExitAction.FAIL, ((1, 2), (4, 9))),
    )
    assert gen.exit_action(15) is ExitAction.RESCHEDULE
    assert gen.exit_action(99) is ExitAction.FAIL


def test_groups_and_inputs(full) -> None:  # type: ignore[no-untyped-def]
    sim = full.groups[1]
    assert sim.barrier is False and sim.ignore_nonlead_status is False
    assert sim.lead.name == "server"
    server = full.task("server")
    assert server.inputs == (InputSpec(task="generate"),
                             InputSpec(task="train", workflow="other-wf-3", regex=r".*\.pt$"))
    assert server.upstream_tasks() == ("generate",)
    assert full.groups[0].barrier and full.groups[0].ignore_nonlead_status


def test_round_trip(full) -> None:  # type: ignore[no-untyped-def]
    assert load_spec(text=dump_yaml(full)) == full
    assert spec_from_dict(spec_to_dict(full)) == full


def test_spec_to_dict_shape(full) -> None:  # type: ignore[no-untyped-def]
    d = spec_to_dict(full)
    assert d["version"] == 2
    wf = d["workflow"]
    assert wf["timeout"] == {"exec_timeout": "7200s", "queue_timeout": "90s"}
    assert wf["resources"]["default"]["memory"] == "8Gi"
    assert wf["maxRetries"] == 2
    gen = wf["groups"][0]["tasks"][0]
    assert gen["exitActions"] == {"COMPLETE": "0", "RESCHEDULE": "3,10-20", "FAIL": "1-2,4-9"}
    assert gen["cache"] is False


BARE = """\
workflow:
  name: bare
  tasks:
  - name: a
    command: [echo, a]
  - name: b
    command: [echo, "{{input:a}}"]
    inputs: [{task: a}]
"""


def test_bare_tasks_are_one_task_groups() -> None:
    spec = load_spec(text=BARE)
    assert spec.bare_tasks
    assert [(g.name, [t.name for t in g.tasks]) for g in spec.groups] == [("a", ["a"]),
                                                                          ("b", ["b"])]
    assert spec.resources == {}
    assert spec.resource_for(spec.task("a")) == ResourceSpec()
    assert spec.task("a").lead is False


def test_set_env_adds_and_overrides() -> None:
    text = BARE.replace("command: [echo, a]", "command: [echo, a]\n    environment: {K: old}")
    spec = load_spec(text=text, set_env=["K=new", "EXTRA=1=2"])
    assert spec.task("a").environment == {"K": "new", "EXTRA": "1=2"}
    assert spec.task("b").environment == {"K": "new", "EXTRA": "1=2"}


def test_malformed_set_items_are_all_reported() -> None:
    with pytest.raises(SpecError) as info:
        load_spec(text=BARE, set_values=["novalue"], set_env=["=x"])
    messages = [d.message for d in info.value.diagnostics]
    assert len(messages) == 2
    assert any("--set 'novalue': expected NAME=VALUE" in m for m in messages)
    assert any("--set-env '=x'" in m for m in messages)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(SpecError) as info:
        load_spec(tmp_path / "nope.yaml")
    [diag] = info.value.diagnostics
    assert diag.line == 0 and "not found" in diag.message
    assert str(diag).startswith(str(tmp_path / "nope.yaml") + ": ")


def test_folder_and_non_utf8(tmp_path: Path) -> None:
    with pytest.raises(SpecError, match="is a folder"):
        load_spec(tmp_path)
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(b"workflow: \xff\n")
    with pytest.raises(SpecError, match="not UTF-8"):
        load_spec(bad)


def test_localpath_relative_to_spec_folder(tmp_path: Path) -> None:
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "run.sh").write_text("echo hi\n")
    spec_file = tmp_path / "sub" / "wf.yaml"
    spec_file.write_text("workflow:\n  name: x\n  tasks:\n  - name: a\n    command: [sh]\n"
                         "    files: [{path: /tmp/run.sh, localpath: run.sh}]\n")
    assert load_spec(spec_file).task("a").files[0].contents == "echo hi\n"


def test_filename_used_in_diagnostics() -> None:
    with pytest.raises(SpecError) as info:
        load_spec(text="workflow: {name: x, tasks: [{name: a}]}", filename="my.yaml")
    assert str(info.value).startswith("my.yaml:1:")


def test_spec_from_dict_rejects_bad_data() -> None:
    with pytest.raises(SpecError):
        spec_from_dict({"workflow": {"name": "x", "tasks": [{"name": "a", "command": [object()]}]}})
    with pytest.raises(SpecError):
        spec_from_dict([])  # type: ignore[arg-type]


def test_yaml_anchors_and_merge_keys() -> None:
    text = ("workflow:\n  name: x\n  resources:\n    default: &d {cpu: 1, gpu: 2}\n"
            "    other: {<<: *d, gpu: 3}\n  tasks:\n  - name: a\n    command: &c [echo]\n"
            "  - name: b\n    command: *c\n")
    spec = load_spec(text=text)
    assert spec.resources["other"] == ResourceSpec(cpu=1, gpu=3)
    assert spec.task("b").command == ("echo",)


def test_alias_bomb_is_bounded() -> None:
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, 8)]
    with pytest.raises(SpecError, match="alias bomb"):
        load_spec(text="\n".join(lines) + "\nworkflow: *a7\n")


def test_cache_is_unset_true_or_false_for_a_task_and_the_workflow() -> None:
    data = {"workflow": {"name": "w", "cache": True, "tasks": [
        {"name": "a", "command": ["true"]}, {"name": "b", "command": ["true"], "cache": False},
        {"name": "c", "command": ["true"], "cache": True, "inputs": [{"task": "a"}]}]}}
    spec = spec_from_dict(data)
    assert spec.cache is True
    assert [spec.task(n).cache for n in "abc"] == [None, False, True]
    assert spec_from_dict(spec_to_dict(spec)) == spec
    assert spec_to_dict(spec)["workflow"]["cache"] is True
    assert "cache" not in spec_to_dict(spec)["workflow"]["tasks"][0]
    # the default: a task another takes as an input reuses, a leaf command task does not
    assert [spec.reuses_by_default(spec.task(n)) for n in "abc"] == [True, False, False]
