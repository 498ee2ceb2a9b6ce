"""Templating: default-values, --set casting, loops, special tokens, sandbox bounds."""

from __future__ import annotations

import pytest

from osmo.errors import SpecError
from osmo.spec import isolation, load_spec, render_spec
from osmo.spec import template as template_module

SPEC = """\
version: 2
default-values:
  shards: 2
  epochs: 3
  lr: 0.1
  tag: v1
  cfg:
    batch: 8
workflow:
  name: templ-{{ tag }}
  tasks:
{% for i in range(shards) %}
  - name: gen-{{ i }}
    command: [gen, --shard, "{{ i }}", --out, "{{output}}"]
{% endfor %}
  - name: train
    command: [train, "{{ epochs }}", "{{ lr }}", "{{ cfg.batch }}", "{{ input:0 }}"]
    inputs:
{% for i in range(shards) %}
    - task: gen-{{ i }}
{% endfor %}
"""


def _messages(exc: pytest.ExceptionInfo[SpecError]) -> list[str]:
    return [str(d) for d in exc.value.diagnostics]


def test_defaults_and_loops() -> None:
    spec = load_spec(text=SPEC)
    assert spec.name == "templ-v1"
    assert [t.name for t in spec.all_tasks()] == ["gen-0", "gen-1", "train"]
    assert spec.task("train").command == ("train", "3", "0.1", "8", "{{ input:0 }}")
    assert spec.task("train").upstream_tasks() == ("gen-0", "gen-1")
    assert spec.task("gen-1").command[-1] == "{{output}}"


def test_set_casts_int_float_string() -> None:
    spec = load_spec(text=SPEC, set_values=["shards=4", "lr=1e-3", "tag=exp2"])
    assert len(spec.all_tasks()) == 5
    assert spec.name == "templ-exp2"
    assert spec.task("train").command[2] == "0.001"


def test_set_string_keeps_string() -> None:
    with pytest.raises(SpecError) as info:
        load_spec(text=SPEC, set_strings=["shards=3"])  # range("3") is a template error
    assert "template error" in _messages(info)[0]
    spec = load_spec(text=SPEC, set_strings=["epochs=010"])
    assert spec.task("train").command[1] == "010"
    assert load_spec(text=SPEC, set_values=["epochs=010"]).task("train").command[1] == "10"


def test_special_tokens_survive_set() -> None:
    spec = load_spec(text=SPEC, set_values=["output=/evil", "input=x", "workflow_id=1"])
    assert spec.task("gen-0").command[-1] == "{{output}}"
    assert spec.task("train").command[-1] == "{{ input:0 }}"


def test_undefined_variable_points_at_its_line() -> None:
    text = "workflow:\n  name: x\n  tasks:\n  - name: a\n    command: [echo, '{{ epoch }}']\n"
    with pytest.raises(SpecError) as info:
        load_spec(text=text, filename="wf.yaml", set_values=["epochs=1"])
    [message] = _messages(info)
    assert message.startswith("wf.yaml:5:25: undefined template variable 'epoch'")
    assert "(did you mean 'epochs'?)" in message and "--set epoch=..." in message


def test_loop_variables_are_not_undefined() -> None:
    text = ("{% set n = 2 %}workflow:\n  name: x\n  tasks:\n"
            "{% for i in range(n) %}  - {name: t{{ i }}, command: [echo, '{{ loop.index }}']}\n"
            "{% endfor %}")
    assert len(load_spec(text=text).groups) == 2


def test_undefined_attribute_at_runtime() -> None:
    text = "default-values:\n  cfg: {a: 1}\nworkflow:\n  name: '{{ cfg.b }}'\n"
    with pytest.raises(SpecError) as info:
        load_spec(text=text, filename="wf.yaml")
    [message] = _messages(info)
    assert message.startswith("wf.yaml:4:1: template error: 'dict object' has no attribute 'b'")


def test_syntax_error_line() -> None:
    with pytest.raises(SpecError) as info:
        load_spec(text="workflow:\n  name: x\n{% if %}\n", filename="wf.yaml")
    assert _messages(info)[0].startswith("wf.yaml:3:1: template syntax error")


def test_sandbox_blocks_internals() -> None:
    with pytest.raises(SpecError, match="template error"):
        load_spec(text="workflow: {name: \"{{ ''.__class__.__mro__ }}\"}\n")


def test_range_and_repeat_limits() -> None:
    with pytest.raises(SpecError, match="exceeds the template limit of 100000"):
        render_spec(text="{% for i in range(100001) %}{% endfor %}")
    with pytest.raises(SpecError, match="too large"):
        render_spec(text="{{ 'x' * 100000000 }}")
    with pytest.raises(SpecError, match="exponents above"):
        render_spec(text="{{ 10 ** 100000 }}")


def test_rendered_size_limit(monkeypatch: pytest.MonkeyPatch) -> None:
    # in this process (the limits are module constants); load_spec renders in a child
    monkeypatch.setattr(isolation, "MAX_RENDERED", 1000)
    rendered, diags = template_module.render(
        "{% for i in range(1000) %}line {{ i }}\n{% endfor %}", "f.yaml", {})
    assert rendered is None and "rendered spec exceeds" in diags[0].message


def test_time_limit_is_checked_as_loops_run() -> None:
    text = "{% for i in range(100000) %}{% for j in range(100000) %}{% endfor %}{% endfor %}"
    rendered, diags = template_module.render(text, "f.yaml", {}, seconds=0.05)
    assert rendered is None and "took longer than 0.05 s, the time limit" in diags[0].message


def test_deep_nesting_is_reported_with_its_position() -> None:
    deep = "{{ " + "(" * 3000 + "1" + ")" * 3000 + " }}"
    with pytest.raises(SpecError) as info:
        render_spec(text=f"a: 1\nb: '{{{{ \"(((\" }}}}' {deep}\n", filename="wf.yaml")
    [message] = _messages(info)
    assert message.startswith(f"wf.yaml:2:{21 + template_module.MAX_NESTING}: template "
                              "expressions nest too deeply: at most 30 levels"), message
    assert render_spec(text="{{ " + "(" * 30 + "1" + ")" * 30 + " }}") == "1"


def test_render_spec_returns_rendered_text() -> None:
    text = render_spec(text=SPEC, set_values=["shards=1"])
    assert "- name: gen-0" in text and "gen-1" not in text
    assert '"{{output}}"' in text and "{{ input:0 }}" in text


def test_default_values_with_template_inside_other_keys() -> None:
    text = ("workflow:\n  name: '{{ n }}'\n  tasks: [{name: a, command: [echo]}]\n"
            "default-values:\n  n: late-defaults\n# trailing comment\n")
    assert load_spec(text=text).name == "late-defaults"


def test_broken_default_values_block() -> None:
    with pytest.raises(SpecError) as info:
        load_spec(text="default-values:\n  a: [1,\nworkflow: {}\n", filename="wf.yaml")
    assert "YAML syntax error" in _messages(info)[0]


def test_variable_in_untaken_branch_is_fine() -> None:
    text = ("workflow:\n  name: x\n  tasks:\n  - name: a\n"
            "    command: [echo{% if gpus is defined %}, '{{ gpus * 2 }}'{% endif %}]\n")
    assert load_spec(text=text).task("a").command == ("echo",)
    assert load_spec(text=text, set_values=["gpus=2"]).task("a").command == ("echo", "4")


def test_every_undefined_variable_is_reported_once() -> None:
    text = ("workflow:\n  name: '{{ a }}'\n  tasks:\n{% for i in range(3) %}"
            "  - {name: 't{{ i }}', command: ['{{ b.c }}', '{{ a }}']}\n{% endfor %}")
    with pytest.raises(SpecError) as info:
        load_spec(text=text, filename="wf.yaml")
    assert [(d.line, d.col, d.message.split(";")[0]) for d in info.value.diagnostics] == [
        (2, 13, "undefined template variable 'a'"),
        (4, 61, "undefined template variable 'b'"),
    ]
