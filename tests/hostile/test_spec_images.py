"""Hostile ``image:`` names are spec errors at ``validate``/``submit`` (exit 2, FILE:LINE:COL).

An image reference must follow the OCI reference grammar (distribution/reference); anything
else (an option, whitespace, a control character, a path, an over-long name) is refused
before anything runs, every bad image of a spec at once.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from osmo.errors import SpecError
from osmo.spec import load_spec
from tests.conftest import Osmo, write

HOSTILE = [
    "--privileged",
    "-v=/:/host",
    "alpine:3.18;id",
    "alpine:3.18 --privileged",
    "alpine\n:3.18",
    "alpine\t",
    "alp\x1bine",
    "alpine\x00",
    "../../etc/passwd",
    "/etc/passwd",
    "Alpine:3.18",  # a repository name is lower case
    "alpine:",
    "alpine:-x",
    "alpine:" + "t" * 129,
    "a/" * 200 + "b",
    "alpine@sha256:xyz",
    "alpine@sha256:" + "a" * 63,
    "alpine@md5",
    "registry.io:port/alpine",
    "registry.io/",
    "a//b",
    "a..b",
    "$(id)",
    "`id`",
    "alpine:{{uuid}}",
]

GOOD = [
    "alpine:3.18",
    "ubuntu",
    "localhost/alpine:3.18",
    "localhost:5000/team/image:v1.0_rc-2",
    "nvcr.io/nvidia/pytorch:24.01-py3",
    "ghcr.io/org/some__img/sub-name:latest",
    "registry.example.com:8443/a.b/c_d",
    "[::1]:5000/img:1",
    "192.168.1.2:5000/img",
    "ubuntu@sha256:" + "ab" * 32,
    "ghcr.io/o/i:v1@sha256:" + "0f" * 32,
]

SPEC = """workflow:
  name: images
  tasks:
  - name: a
    image: %s
    command: ["true"]
"""


@pytest.mark.parametrize("image", HOSTILE, ids=range(len(HOSTILE)))
def test_a_hostile_image_is_a_spec_error_at_its_position(tmp_path: Path, image: str) -> None:
    spec = write(tmp_path / "wf.yaml", SPEC % json.dumps(image))
    with pytest.raises(SpecError) as info:
        load_spec(spec)
    [problem] = info.value.diagnostics
    assert (problem.line, problem.col) == (5, 12), problem
    assert "'image' of task 'a'" in problem.message and "image reference" in problem.message


@pytest.mark.parametrize("image", GOOD)
def test_an_image_reference_of_the_oci_grammar_is_accepted(tmp_path: Path, image: str) -> None:
    spec = write(tmp_path / "wf.yaml", SPEC % json.dumps(image))
    assert load_spec(spec).groups[0].tasks[0].image == image


def test_validate_and_submit_refuse_every_bad_image_at_once(osmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "bad.yaml", """workflow:
  name: images
  tasks:
  - name: a
    image: --privileged
    command: ["true"]
  - name: b
    image: "alpine:3.18 --net=host"
    command: ["true"]
  - name: c
    image: alpine:3.18
    command: ["true"]
""")
    for verb in ("validate", "submit"):
        r = osmo(verb, str(spec))
        assert r.code == 2, r
        assert f"{spec}:5:12: 'image' of task 'a'" in r.err
        assert f"{spec}:8:12: 'image' of task 'b'" in r.err
        assert "Traceback" not in r.err
    assert osmo("list", "--format", "json", check=True).json() == []
