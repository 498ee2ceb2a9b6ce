"""url: inputs and outputs end to end, over file:// and a real S3-compatible server."""

from __future__ import annotations

import json
import time
from pathlib import Path

from osmo.urls import for_url
from tests.conftest import Osmo, ended, write
from tests.urls.conftest import s3_bucket, s3_credential, s3_endpoint  # noqa: F401

PRODUCE = """
workflow:
  name: produce
  tasks:
  - name: make
    command: [sh, -c, "mkdir -p {{output}}/a; echo one > {{output}}/a/1.txt; echo two > {{output}}/2.txt; echo skip > {{output}}/x.log"]
    outputs:
    - url: URL
      regex: "\\\\.txt$"
"""

CONSUME = """
workflow:
  name: consume
  tasks:
  - name: read
    command: [sh, -c, "cat {{input:0}}/a/1.txt {{input:0}}/2.txt > {{output}}/both.txt; ls {{input:0}}"]
    inputs:
    - url: URL
"""


def _run(osmo: Osmo, text: str, path: Path, *args: str) -> dict:
    r = osmo("submit", str(write(path, text)), "--wait", *args)
    info = osmo.query(r.out.splitlines()[0].split(" - ")[1])
    info["code"] = r.code
    return info


def test_file_url_output_then_input(osmo: Osmo, tmp_path: Path) -> None:
    url = f"file://{tmp_path}/remote/run1"
    made = _run(osmo, PRODUCE.replace("URL", url), tmp_path / "p.yaml")
    assert made["code"] == 0, made
    remote = tmp_path / "remote" / "run1"
    assert (remote / "a" / "1.txt").read_text() == "one\n"
    assert not (remote / "x.log").exists()  # regex filtered it out
    marker = json.loads((remote / ".osmo-complete.json").read_text())
    assert marker  # the completion marker lists what was uploaded
    used = _run(osmo, CONSUME.replace("URL", url), tmp_path / "c.yaml")
    assert used["code"] == 0, used
    both = Path(used["tasks"][0]["output"]) / "both.txt"
    assert both.read_text() == "one\ntwo\n"


def test_a_failed_upload_fails_the_task_and_marks_nothing(osmo: Osmo, tmp_path: Path) -> None:
    blocker = tmp_path / "remote"
    blocker.write_text("a file where the upload needs a folder")
    made = _run(osmo, PRODUCE.replace("URL", f"file://{blocker}/run"), tmp_path / "p.yaml")
    assert made["code"] == 1
    task = made["tasks"][0]
    assert task["status"] == "FAILED" and task["output"] is None
    assert "upload of outputs failed" in task["message"]


def test_missing_url_input_fails_the_start_clearly(osmo: Osmo, tmp_path: Path) -> None:
    used = _run(osmo, CONSUME.replace("URL", f"file://{tmp_path}/nothing"), tmp_path / "c.yaml")
    assert used["code"] == 1
    task = used["tasks"][0]
    assert task["status"] == "FAILED_START_ERROR" and "nothing" in task["message"]


def test_s3_output_and_input_with_a_stored_credential(
        osmo: Osmo, tmp_path: Path, s3_bucket: str,  # noqa: F811
        s3_credential: dict[str, str]) -> None:  # noqa: F811
    osmo("credential", "set", "s3",
         *[arg for k, v in s3_credential.items() for arg in ("--payload", f"{k}={v}")],
         check=True)
    listed = osmo("credential", "list", check=True).out
    assert "s3" in listed and s3_credential["secret_key"] not in listed
    url = f"s3://{s3_bucket}/runs/one"
    made = _run(osmo, PRODUCE.replace("URL", url), tmp_path / "p.yaml")
    assert made["code"] == 0, made
    pulled = tmp_path / "pulled"
    assert sorted(for_url(url, s3_credential).download(pulled)) == ["2.txt", "a/1.txt"]
    used = _run(osmo, CONSUME.replace("URL", url), tmp_path / "c.yaml")
    assert used["code"] == 0, used
    assert (Path(used["tasks"][0]["output"]) / "both.txt").read_text() == "one\ntwo\n"
    logs = osmo("logs", used["id"]).out + osmo("logs", made["id"]).out
    assert s3_credential["secret_key"] not in logs


CHECKPOINTED = """
workflow:
  name: train
  tasks:
  - name: fit
    command: [sh, -c, "mkdir -p {{output}}/ckpt; i=0; while [ ! -e RELEASE ]; do i=$((i+1)); echo step $i > {{output}}/ckpt/state.txt; sleep 0.1; done; echo final > {{output}}/ckpt/state.txt"]
    checkpoint:
    - path: "{{output}}/ckpt"
      url: URL
      frequency: 1s
"""


def test_checkpoints_upload_while_running_and_at_the_end(osmo: Osmo, tmp_path: Path) -> None:
    remote, release = tmp_path / "ckpts", tmp_path / "release"
    spec = write(tmp_path / "t.yaml", CHECKPOINTED.replace("URL", f"file://{remote}")
                 .replace("RELEASE", str(release)))
    wf = osmo.submit(spec)
    deadline = time.monotonic() + 60
    while not (remote / ".osmo-complete.json").exists():  # a periodic upload landed
        assert time.monotonic() < deadline, "no checkpoint was uploaded while running"
        time.sleep(0.1)
    assert osmo.query(wf)["tasks"][0]["status"] == "RUNNING"
    assert (remote / "state.txt").read_text().startswith("step ")
    release.write_text("go")
    info = osmo.wait_for(wf, ended)
    assert info["status"] == "COMPLETED"
    assert (remote / "state.txt").read_text() == "final\n"  # the last upload at the end
    assert "checkpoint uploaded to" in osmo("logs", wf, "-t", "fit").out


def test_a_failed_final_checkpoint_fails_the_task(osmo: Osmo, tmp_path: Path) -> None:
    blocker = tmp_path / "blocked"
    blocker.write_text("a file where the checkpoint folder should go")
    release = tmp_path / "release"
    release.write_text("go")  # finish at once
    spec = write(tmp_path / "t.yaml", CHECKPOINTED.replace("URL", f"file://{blocker}/x")
                 .replace("RELEASE", str(release)))
    r = osmo("submit", str(spec), "--wait")
    assert r.code == 1
    task = osmo.query(r.out.splitlines()[0].split(" - ")[1])["tasks"][0]
    assert task["status"] == "FAILED" and "final checkpoint upload failed" in task["message"]
    assert task["output"] is None
