"""Datasets end to end: versions made by tasks, tags, consumption, upload/download, lineage."""

from __future__ import annotations

import json
from pathlib import Path

from tests.conftest import Osmo, write

MAKE = r"""
workflow:
  name: make
  tasks:
  - name: gen
    command: [sh, -c, "mkdir -p {{output}}/eps {{output}}/tmp; for i in $(seq 1 {{n}}); do echo ep$i > {{output}}/eps/e$i.txt; done; echo x > {{output}}/tmp/t.log; echo {{n}} > {{output}}/eps/count.csv"]
    outputs:
    - dataset: {name: demos, path: eps, regex: "\\.txt$", metadata: {robot: pendulum}}
"""

USE = r"""
workflow:
  name: use
  tasks:
  - name: read
    command: [sh, -c, "ls {{input:0}} | tr '\\n' ' ' > {{output}}/seen.txt"]
    inputs:
    - dataset: {name: "demos:REF"}
"""


def _wf(osmo: Osmo, spec: Path, *args: str) -> str:
    r = osmo("submit", str(spec), "--wait", *args)
    assert r.code == 0, r.out + r.err
    return r.out.splitlines()[0].split(" - ")[1]


def _datasets(osmo: Osmo) -> list[dict]:
    return json.loads(osmo("dataset", "list", "--format", "json", check=True).out)


def test_versions_tags_and_consumption(osmo: Osmo, tmp_path: Path) -> None:
    make = write(tmp_path / "make.yaml", MAKE)
    _wf(osmo, make, "--set", "n=2")
    _wf(osmo, make, "--set", "n=3")
    versions = {d["version"]: d for d in _datasets(osmo)}
    assert set(versions) == {1, 2}
    assert versions[1]["files"] == 2 and versions[2]["files"] == 3  # path + regex applied
    assert versions[1]["metadata"] == {"robot": "pendulum"}
    info = json.loads(osmo("dataset", "info", "demos:1", "--format", "json", check=True).out)
    assert [f["path"] for f in info["files"]] == ["e1.txt", "e2.txt"]
    newest = json.loads(osmo("dataset", "info", "demos", "--format", "json", check=True).out)
    assert newest["version"] == 2
    # Versions share blobs: e1.txt and e2.txt are the same content in both.
    assert {f["digest"] for f in info["files"]} <= {f["digest"] for f in newest["files"]}
    osmo("dataset", "tag", "demos:1", "golden", check=True)
    wf = ""
    for ref, expected in (("golden", "e1.txt e2.txt "), ("latest", "e1.txt e2.txt e3.txt "),
                          ("2", "e1.txt e2.txt e3.txt ")):
        use = write(tmp_path / f"use-{ref}.yaml", USE.replace("REF", ref))
        wf = _wf(osmo, use)
        out = json.loads(osmo("artifacts", "list", wf, "read", "--format", "json").out)[0]
        assert (Path(out["path"]) / "seen.txt").read_text() == expected
    graph = json.loads(osmo("lineage", f"{wf}:read", "--format", "json", check=True).out)
    tasks = {str(n.get("task")) for n in graph["nodes"].values()}
    assert "gen" in tasks and "dataset demos:2" in tasks


def test_missing_dataset_fails_the_task_with_a_clear_message(osmo: Osmo,
                                                             tmp_path: Path) -> None:
    use = write(tmp_path / "use.yaml", USE.replace("REF", "9"))
    r = osmo("submit", str(use), "--wait")
    assert r.code == 1
    task = osmo.query(r.out.splitlines()[0].split(" - ")[1])["tasks"][0]
    assert task["status"] == "FAILED_START_ERROR"
    assert "dataset 'demos:9' does not exist" in task["message"]


def test_upload_download_and_the_callers_files_stay_writable(osmo: Osmo,
                                                             tmp_path: Path) -> None:
    src = tmp_path / "mine"
    write(src / "a.txt", "alpha\n")
    write(src / "sub" / "b.bin", "beta\n")
    assert osmo("dataset", "upload", "hand", str(src), "--metadata", "by=me",
                check=True).out.strip() == "hand:1"
    (src / "a.txt").write_text("still mine\n")  # the upload copied; the source is untouched
    dest = tmp_path / "back"
    osmo("dataset", "download", "hand:1", "-o", str(dest), check=True)
    assert (dest / "a.txt").read_text() == "alpha\n"
    assert (dest / "sub" / "b.bin").read_text() == "beta\n"
    assert _datasets(osmo)[0]["made_by"] is None


TAMPER_FILE = r"""
    files:
    - path: /opt/tamper.sh
      contents: |
        d=$1
        try() { if "$@" 2>/dev/null; then echo "allowed: $*"; else echo "denied: $*"; fi; }
        {
          try sh -c 'echo evil >> "$1"' - "$d/a.txt"
          try touch "$d/new.txt"
          try rm "$d/sub/b.txt"
          try chmod 777 "$d/a.txt"
        } > "$2"
"""
"""A task's ``files:`` entry: ``sh /opt/tamper.sh FOLDER REPORT`` tries 4 changes in FOLDER
(``a.txt``, ``sub/b.txt``) and writes ``allowed: ...`` or ``denied: ...`` for each."""

TAMPER = r"""
workflow:
  name: tamper
  tasks:
  - name: t
    command: [sh, /opt/tamper.sh, "{{input:0}}", "{{output}}/ops.txt"]""" + TAMPER_FILE + """\
    inputs:
    - dataset: {name: kept}
"""


READ = r"""
workflow:
  name: read
  tasks:
  - name: t
    command: [sh, -c, "cat {{input:0}}/a.txt {{input:0}}/sub/b.txt > {{output}}/seen.txt 2>&1; exit 0"]
    inputs:
    - dataset: {name: kept}
"""


def test_dataset_inputs_are_read_only(osmo: Osmo, tmp_path: Path) -> None:
    """A dataset version is handed to a task read-only (DESIGN: inputs read-only): the process
    sandbox binds it read-only, so append, create, delete and chmod all fail."""
    src = tmp_path / "data"
    write(src / "a.txt", "alpha\n")
    write(src / "sub" / "b.txt", "beta\n")
    osmo("dataset", "upload", "kept", str(src), check=True)
    spec = write(tmp_path / "tamper.yaml", TAMPER)
    tampered = (Path(osmo.query(_wf(osmo, spec))["tasks"][0]["output"]) / "ops.txt").read_text()
    assert "allowed" not in tampered, tampered
    read = _wf(osmo, write(tmp_path / "read.yaml", READ))
    seen = (Path(osmo.query(read)["tasks"][0]["output"]) / "seen.txt").read_text()
    assert seen == "alpha\nbeta\n", "a later consumer saw another task's changes"


def test_dataset_inputs_are_private(osmo: Osmo, tmp_path: Path) -> None:
    """Without a sandbox, whatever a task does to its dataset input, the next consumer of the
    version reads the version as uploaded (each attempt gets its own checked copy)."""
    osmo("server", "start", "--sandbox", "off", check=True)
    src = tmp_path / "data"
    write(src / "a.txt", "alpha\n")
    write(src / "sub" / "b.txt", "beta\n")
    osmo("dataset", "upload", "kept", str(src), check=True)
    tampered = (Path(osmo.query(_wf(osmo, write(tmp_path / "tamper.yaml", TAMPER)))["tasks"][0]
                     ["output"]) / "ops.txt").read_text()
    assert "allowed: sh -c" in tampered, tampered  # the task did write to its own copy
    read = _wf(osmo, write(tmp_path / "read.yaml", READ))
    seen = (Path(osmo.query(read)["tasks"][0]["output"]) / "seen.txt").read_text()
    assert seen == "alpha\nbeta\n", "a later consumer saw another task's changes"
