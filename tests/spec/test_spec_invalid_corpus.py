"""Every file in ``invalid/`` is rejected with exactly the diagnostics its header declares.

A header line ``# expect: LINE:COL: text`` asserts one diagnostic at that position whose message
contains ``text``. The number of diagnostics must equal the number of expectations. Task
types resolve as in the CLI: custom ``module:attr`` types from the file's folder
(``corpus_types.py``).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from osmo.errors import SpecError
from osmo.spec import load_spec
from osmo.tasktypes.registry import Resolver

CORPUS = Path(__file__).parent / "invalid"
FILES = sorted(CORPUS.glob("*.yaml"))
EXPECT = re.compile(r"^# expect: (\d+):(\d+): (.*)$")


def _expectations(path: Path) -> list[tuple[int, int, str]]:
    out = []
    for line in path.read_text().splitlines():
        match = EXPECT.match(line)
        if match:
            out.append((int(match[1]), int(match[2]), match[3].strip()))
    return out


def test_corpus_is_large_enough() -> None:
    assert len(FILES) >= 30


@pytest.mark.parametrize("path", FILES, ids=[p.stem for p in FILES])
def test_invalid_spec(path: Path) -> None:
    expected = _expectations(path)
    assert expected, f"{path.name} declares no '# expect:' lines"
    with pytest.raises(SpecError) as info:
        load_spec(path, types=Resolver([str(path.parent)]))  # as the CLI resolves types
    got = info.value.diagnostics
    shown = "\n".join(str(d) for d in got)
    for line, col, text in expected:
        assert any(d.line == line and d.col == col and text in d.message for d in got), (
            f"missing {line}:{col}: {text!r} in:\n{shown}")
    assert len(got) == len(expected), f"unexpected diagnostics:\n{shown}"
    assert all(d.file == str(path) for d in got)
