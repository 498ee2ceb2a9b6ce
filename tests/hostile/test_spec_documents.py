"""Hostile spec documents: deep nesting, huge numbers and unknown YAML tags.

Each is an exit-2 error at ``FILE:LINE:COL`` that states the limit or names the tag, never a
traceback or a crash (libyaml's composer recursed in C and took the process down at ~100,000
levels).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from osmo.errors import SpecError
from osmo.spec import load_spec
from osmo.spec.yamlnodes import MAX_DEPTH, load_nodes
from tests.conftest import REPO, write

HEAD = "workflow:\n  name: deep\n  tasks:\n  - name: a\n    command: [echo]\n"


def _validate(path: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "osmo", "validate", str(path)],
                          capture_output=True, text=True, timeout=120, cwd=REPO)


def _flow(depth: int) -> str:
    return "[" * depth + "]" * depth


@pytest.mark.parametrize("depth", [MAX_DEPTH + 1, 1000, 100_000, 1_000_000])
def test_deep_flow_yaml_is_refused_with_its_position(tmp_path: Path, depth: int) -> None:
    spec = write(tmp_path / "deep.yaml", HEAD + f"    args: {_flow(depth)}\n")
    r = _validate(spec)
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    # args' first bracket (column 11) is level 5: document, workflow, tasks, task, args
    assert f"{spec}:6:{11 + MAX_DEPTH - 4}: YAML nested more than {MAX_DEPTH} levels deep" \
        in r.stderr, r.stderr[-2000:]
    assert "Traceback" not in r.stderr


def test_deep_block_yaml_is_refused(tmp_path: Path) -> None:
    spec = write(tmp_path / "deep.yaml", HEAD + "    args:\n" + "    " + "- " * 5000 + "x\n")
    r = _validate(spec)
    assert r.returncode == 2 and "levels deep" in r.stderr and "Traceback" not in r.stderr, r


def test_deep_default_values_are_refused(tmp_path: Path) -> None:
    spec = write(tmp_path / "deep.yaml", f"default-values:\n  x: {_flow(50_000)}\n" + HEAD
                 + "    args: ['{{ x }}']\n")
    r = _validate(spec)
    assert r.returncode == 2 and f"{spec}:2:" in r.stderr and "levels deep" in r.stderr, r


def test_aliases_cannot_nest_past_the_limit() -> None:
    half = MAX_DEPTH // 2 + 10
    text = (f"a: &a {'[' * half}1{']' * half}\n"
            f"b: &b {'[' * half}*a{']' * half}\n")
    root, diags = load_nodes(text, "f.yaml")
    assert root is None and len(diags) == 1
    assert str(diags[0]).startswith("f.yaml:1:") and "levels deep" in str(diags[0])


def test_nesting_up_to_the_limit_is_fine() -> None:
    depth = MAX_DEPTH - 1
    root, diags = load_nodes(f"a: {_flow(depth)}\n" + "# padding\n" * 300, "f.yaml")
    assert diags == [] and root is not None


def test_deep_template_expression_is_refused_with_its_position(tmp_path: Path) -> None:
    spec = write(tmp_path / "deep.yaml", HEAD + "    args: ['{{ " + "(" * 3000 + "1"
                 + ")" * 3000 + " }}']\n")
    r = _validate(spec)
    assert r.returncode == 2, r.stderr[-2000:]
    assert f"{spec}:6:" in r.stderr and "at most 30 levels" in r.stderr
    assert "Traceback" not in r.stderr


def test_huge_integer_is_refused_with_its_position(tmp_path: Path) -> None:
    spec = write(tmp_path / "big.yaml", HEAD + "    args: [" + "9" * 5000 + "]\n")
    r = _validate(spec)
    assert r.returncode == 2, r.stderr[-2000:]
    assert f"{spec}:6:12: this number has 5000 characters; integers may have at most " \
           f"{sys.get_int_max_str_digits()} digits" in r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize("value,tag", [
    ("!!python/object/apply:os.system [ls]", "!!python/object/apply:os.system"),
    ("!!python/name:os.system ''", "!!python/name:os.system"),
    ("!foo bar", "!foo"),
    ("!foo [1, 2]", "!foo"),
    ("!!binary aGk=", "!!binary"),
    ("!!set {a, b}", "!!set"),
])
def test_unknown_tags_are_refused_by_name(value: str, tag: str) -> None:
    with pytest.raises(SpecError) as info:
        load_spec(text=HEAD + f"    args: {value}\n", filename="t.yaml")
    [diag] = info.value.diagnostics
    assert (diag.line, diag.col) == (6, 11)
    assert diag.message.startswith(f"unknown YAML tag '{tag}': osmo reads plain YAML values")


def test_a_tagged_key_is_refused() -> None:
    with pytest.raises(SpecError, match="t.yaml:1:1: unknown YAML tag '!k'"):
        load_spec(text="!k workflow: {name: x, tasks: [{name: a, command: [echo]}]}\n",
                  filename="t.yaml")


def test_plain_tags_still_work() -> None:
    spec = load_spec(text=HEAD + "    args: [!!str 1, !!int '2', ! three]\n")
    assert spec.task("a").args == ("1", "2", "three")
