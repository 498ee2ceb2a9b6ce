"""The public surface of ``osmo.spec`` and its layering rules."""

from __future__ import annotations

import re
from pathlib import Path

import osmo.spec

SPEC_DIR = Path(osmo.spec.__file__).parent
API = {"load_spec", "render_spec", "spec_to_dict", "dump_yaml", "spec_from_dict", "Workflow",
       "Task"}


def test_exported_members_exist_and_are_documented() -> None:
    assert set(osmo.spec.__all__) >= API
    for name in osmo.spec.__all__:
        member = getattr(osmo.spec, name)
        assert getattr(member, "__doc__", None) or isinstance(member, str), name


def test_third_party_imports_stay_in_their_adapter() -> None:
    owners = {"yaml": "yamlnodes.py", "jinja2": "template.py"}
    for path in SPEC_DIR.glob("*.py"):
        source = path.read_text()
        for lib, owner in owners.items():
            if re.search(rf"^\s*(import|from) {lib}\b", source, re.MULTILINE):
                assert path.name == owner, f"{path.name} imports {lib}"


def test_modules_are_small_and_documented() -> None:
    for path in SPEC_DIR.glob("*.py"):
        source = path.read_text()
        assert len(source.splitlines()) < 400, path.name
        assert source.lstrip().startswith('"""'), f"{path.name} has no module docstring"
        assert "from __future__ import annotations" in source, path.name
