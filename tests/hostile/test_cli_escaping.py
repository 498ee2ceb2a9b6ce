"""Names a task chose are printed escaped (as ``ls --escape`` does), JSON keeps them exact.

A file called ``\\x1b]0;owned\\x07`` retitled the terminal when ``osmo artifacts list`` printed
it, and a newline in a name forged a line. Every place the CLI prints such names goes through
``osmo.cli.render.safe``.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from osmo.cli.render import format_log, safe
from osmo.sdk.client import LogRecord
from tests.conftest import Osmo, write

EVIL = ["title\x1b]0;owned\x07.txt", "forged\nline.txt", "tab\tname.txt",
        "rtl\u202etxt.exe", "plain-caf\u00e9.txt"]

SPEC = """
workflow:
  name: evil
  tasks:
  - name: make
    command: [python3, -c, "import os, sys; [open(os.path.join(sys.argv[1], n), 'w').write('x') for n in sys.argv[2:]]", "{{output}}", NAMES]
""".replace("NAMES", ", ".join(json.dumps(n) for n in EVIL))


@pytest.mark.parametrize("raw,shown", [
    ("plain-name_1.txt", "plain-name_1.txt"),
    ("café ünïcode", "café ünïcode"),
    ("title\x1b]0;owned\x07", "title\\033]0;owned\\a"),
    ("a\nb\rc\td", "a\\nb\\rc\\td"),
    ("clear\x1b[2J\x1b[H", "clear\\033[2J\\033[H"),
    ("back\\slash", "back\\\\slash"),
    ("rtl\u202eexe", "rtl\\u202eexe"),
    ("del\x7f c1\x9b", "del\\177 c1\\233"),
    ("latin1 caf\udce9", "latin1 caf\\351"),
    ("tag\U000e0041", "tag\\U000e0041"),
])
def test_safe_escapes_what_a_terminal_would_act_on(raw: str, shown: str) -> None:
    assert safe(raw) == shown
    assert safe(raw).isprintable()


def test_log_headers_are_escaped() -> None:
    line = format_log(LogRecord(0.0, "t\x1b[2J\nforged", 1, "stdout", "hello"))
    assert "\x1b" not in line and "\n" not in line and "[t\\033[2J\\nforged retry-1]" in line


def test_artifacts_and_lineage_print_hostile_names_escaped(osmo: Osmo, tmp_path: Path) -> None:
    wf = osmo.submit(write(tmp_path / "evil.yaml", SPEC), "--wait")
    listed = osmo("artifacts", "list", wf, check=True).out
    assert "\x1b" not in listed and "\x07" not in listed and "\u202e" not in listed
    assert "title\\033]0;owned\\a.txt" in listed and "forged\\nline.txt" in listed
    assert "tab\\tname.txt" in listed and "rtl\\u202etxt.exe" in listed
    assert "plain-café.txt" in listed
    assert len(listed.splitlines()) == 1 + len(EVIL)  # one line per file: none forged
    exact = json.loads(osmo("artifacts", "list", wf, "--format", "json", check=True).out)
    assert sorted(f["path"] for f in exact[0]["files"]) == sorted(EVIL)
    lineage = osmo("lineage", f"{wf}:make", check=True).out
    assert "\x1b" not in lineage and len(lineage.splitlines()) == 1
    verbose = osmo("query", wf, "-v", check=True).out
    assert "\x1b" not in verbose
