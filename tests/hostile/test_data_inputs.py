"""Hostile readers: a task that writes to its inputs changes nothing anyone else reads, and a
blob that no longer matches its digest is never handed out (issue 11, item 5).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from tests.conftest import Osmo, write
from tests.hostile.datarun import finished, tasks

PIPELINE = """
workflow:
  name: shared
  tasks:
  - name: make
    command: [sh, -c, "echo original > {{output}}/data.txt"]
  - name: tamper
    inputs: [{task: make}]
    command: [sh, -c, "echo x >> {{input:0}}/data.txt; chmod 666 {{input:0}}/data.txt; echo y >> {{input:0}}/data.txt; rm -f {{input:0}}/gone; echo done > {{output}}/t"]
  - name: after
    inputs: [{task: tamper}, {task: make}]
    command: [sh, -c, "cat {{input:make}}/data.txt > {{output}}/seen"]
"""

READER = """
workflow:
  name: reader
  tasks:
  - name: read
    inputs: [{{task: "{wf}:make"}}]
    command: [sh, -c, "cat {{{{input:0}}}}/data.txt > {{{{output}}}}/seen"]
"""


def _output(osmo: Osmo, wf: str, task: str) -> Path:
    return Path(tasks(osmo, wf)[task]["output"])


def test_a_task_appending_to_its_input_changes_nobody_elses(osmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "p.yaml", PIPELINE)
    wf = finished(osmo, spec)
    assert (_output(osmo, wf, "after") / "seen").read_text() == "original\n"
    reader = finished(osmo, write(tmp_path / "r.yaml", READER.format(wf=wf)))
    assert (_output(osmo, reader, "read") / "seen").read_text() == "original\n"
    got = tmp_path / "got"
    osmo("artifacts", "get", f"{wf}:make", "-o", str(got), check=True)
    assert (got / "data.txt").read_text() == "original\n"
    again = finished(osmo, spec)  # make is a cache hit now: its readers still get the original
    assert (_output(osmo, again, "after") / "seen").read_text() == "original\n"
    blob = osmo.home / "artifacts" / "blobs" / "sha256" / _hex(b"original\n")[:2] / _hex(
        b"original\n")[2:]
    assert blob.read_bytes() == b"original\n"


def test_a_blob_that_no_longer_matches_is_never_handed_out(osmo: Osmo, tmp_path: Path) -> None:
    wf = finished(osmo, write(tmp_path / "p.yaml", PIPELINE))
    hex_ = _hex(b"original\n")
    blob = osmo.home / "artifacts" / "blobs" / "sha256" / hex_[:2] / hex_[2:]
    blob.chmod(0o644)
    blob.write_bytes(b"tampered\n")  # what a root task could do to the store itself
    reader = finished(osmo, write(tmp_path / "r.yaml", READER.format(wf=wf)), code=1)
    read = tasks(osmo, reader)["read"]
    assert read["status"] == "FAILED_START_ERROR", read
    assert f"sha256:{hex_}" in read["message"] and "now hashes to" in read["message"]
    got = osmo("artifacts", "get", f"{wf}:make", "-o", str(tmp_path / "got"))
    assert got.code == 3 and "now hashes to" in got.err, got.out + got.err
    assert not (tmp_path / "got" / "data.txt").exists()


def _hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()
