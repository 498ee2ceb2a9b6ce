"""Hostile file names: a task's output names are bytes, end to end (issue 11, item 1).

Names that are not UTF-8 (Latin-1 ``caf\\xe9.csv``), or hold control characters, go through
ingest, the manifest, the state store, lineage, the run record and ``osmo artifacts get``,
and come back as the same bytes. The server keeps serving other workflows.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from osmo.record import read_run_record
from tests.conftest import Osmo, write
from tests.hostile.datarun import finished

NAMES = {b"caf\xe9.csv": b"latin-1\n", "na\u00efve.txt".encode(): b"utf-8\n",
         b"d\xff/in\x01side": b"control\n", b"d\xff/new\nline": b"newline\n"}

WRITER = """
import os
out = os.environb[b"OSMO_OUTPUT"]
os.mkdir(out + b"/d\\xff")
for name, data in {names!r}.items():
    with open(out + b"/" + name, "wb") as f:
        f.write(data)
"""

SPEC = """
workflow:
  name: latin
  tasks:
  - name: make
    command: [python3, /tmp/w.py]
    files:
    - path: /tmp/w.py
      contents: |
{script}
  - name: use
    inputs: [{{task: make}}]
    command: [sh, -c, "cat {{{{input:make}}}}/caf*.csv > {{{{output}}}}/copied"]
"""


def _spec(tmp_path: Path) -> Path:
    script = "\n".join("        " + line for line in WRITER.format(names=NAMES).splitlines())
    return write(tmp_path / "latin.yaml", SPEC.format(script=script))


def _tree(root: Path) -> dict[bytes, bytes]:
    out: dict[bytes, bytes] = {}
    base = os.fsencode(root)
    for folder, _dirs, files in os.walk(base):
        for name in files:
            path = os.path.join(folder, name)
            with open(path, "rb") as f:
                out[os.path.relpath(path, base)] = f.read()
    return out


def test_non_utf8_output_names_round_trip_and_the_server_keeps_serving(
        osmo: Osmo, tmp_path: Path) -> None:
    wf = finished(osmo, _spec(tmp_path))

    dest = tmp_path / "got"
    got = osmo("artifacts", "get", f"{wf}:make", "-o", str(dest))
    assert got.code == 0, got.out + got.err
    assert _tree(dest) == NAMES  # the exact bytes of every name, and the contents
    assert "caf\\351.csv" in got.out  # printed escaped, never raw bytes

    one = tmp_path / "one"
    got = osmo("artifacts", "get", f"{wf}:make:" + os.fsdecode(b"caf\xe9.csv"), "-o", str(one))
    assert got.code == 0, got.out + got.err
    assert os.listdir(os.fsencode(one)) == [b"caf\xe9.csv"]

    listed = json.loads(osmo("artifacts", "list", wf, "make", "--format", "json",
                             check=True).out)
    assert sorted(os.fsencode(f["path"]) for f in listed[0]["files"]) == sorted(NAMES)
    text = osmo("artifacts", "list", wf, "make", check=True).out
    assert "caf\\351.csv" in text and "d\\377/in\\001side" in text and "new\\nline" in text
    assert "\x01" not in text

    # the downstream task saw the same name; the run record was written and reads back
    assert osmo("logs", wf, check=True).code == 0
    record = osmo.home / "runs" / wf / "run.mcap"
    deadline = time.monotonic() + 30
    while not record.exists():
        assert time.monotonic() < deadline, "the run record was never written"
        time.sleep(0.1)
    assert {m["status"] for m in read_run_record(record)["status"]} >= {"COMPLETED"}

    # the server still serves everyone else
    other = write(tmp_path / "ok.yaml", """
workflow:
  name: other
  tasks:
  - name: t
    command: [sh, -c, "echo fine > {{output}}/f"]
""")
    finished(osmo, other)
