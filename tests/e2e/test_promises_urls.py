"""docs/how-to/credentials.md, S3 and other data URLs: a ``s3://BUCKET`` credential is used in preference to ``s3``; tasks with
``url:`` inputs or outputs are never cached; a failed periodic checkpoint upload is logged
and tried again. Through the real CLI, against a real s3rver for S3."""

from __future__ import annotations

import time
from pathlib import Path

from osmo.config import free_port
from osmo.urls import for_url
from tests.conftest import Osmo, ended, write
from tests.urls.conftest import s3_bucket, s3_credential, s3_endpoint  # noqa: F401


def _payload(cred: dict[str, str]) -> list[str]:
    return [arg for k, v in cred.items() for arg in ("--payload", f"{k}={v}")]


def _submit_wait(osmo: Osmo, spec: Path) -> dict:
    r = osmo("submit", str(spec), "--wait")
    info = osmo.query(r.out.splitlines()[0].split(" - ")[1])
    info["code"] = r.code
    return info


def test_a_bucket_credential_wins_over_the_generic_one(
        osmo: Osmo, tmp_path: Path, s3_bucket: str,  # noqa: F811
        s3_credential: dict[str, str]) -> None:  # noqa: F811
    nowhere = f"http://127.0.0.1:{free_port(0)}"  # nothing listens there
    osmo("credential", "set", "s3", *_payload(
        {"endpoint": nowhere, "access_key": "WRONG", "secret_key": "WRONG"}), check=True)
    osmo("credential", "set", f"s3://{s3_bucket}", *_payload(s3_credential), check=True)
    spec = """
workflow:
  name: to-s3
  tasks:
  - name: make
    command: [sh, -c, "echo made > {{output}}/made.txt"]
    outputs:
    - url: URL
"""
    made = _submit_wait(osmo, write(tmp_path / "ok.yaml",
                                    spec.replace("URL", f"s3://{s3_bucket}/out")))
    assert made["code"] == 0, made
    pulled = tmp_path / "pulled"
    assert for_url(f"s3://{s3_bucket}/out", s3_credential).download(pulled) == ["made.txt"]
    assert (pulled / "made.txt").read_text() == "made\n"
    # another bucket has no credential of its own: the generic one is used, and it is bad
    other = _submit_wait(osmo, write(tmp_path / "other.yaml",
                                     spec.replace("URL", "s3://other-bucket/out")))
    assert other["code"] == 1
    assert nowhere.split("//")[1] in other["tasks"][0]["message"], other


def test_url_tasks_are_never_cached(osmo: Osmo, tmp_path: Path) -> None:
    (tmp_path / "seed").mkdir()
    (tmp_path / "seed" / "seed.txt").write_text("42\n")
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: urls-uncached
  cache: true
  tasks:
  - name: plain
    command: [sh, -c, "echo x >> TMP/plain-runs; echo p > {{output}}/p"]
  - name: up
    command: [sh, -c, "echo x >> TMP/up-runs; echo u > {{output}}/u"]
    outputs:
    - url: file://TMP/remote/up
  - name: down
    command: [sh, -c, "echo x >> TMP/down-runs; cat {{input:0}}/seed.txt > {{output}}/seed"]
    inputs:
    - url: file://TMP/seed
""".replace("TMP", str(tmp_path)))
    first, second = _submit_wait(osmo, spec), _submit_wait(osmo, spec)
    assert first["code"] == second["code"] == 0, (first, second)
    reused = {t["name"]: t["reused"] for t in second["tasks"]}
    assert reused == {"plain": True, "up": False, "down": False}  # caching is on, but not here
    runs = {n: len((tmp_path / f"{n}-runs").read_text().split()) for n in reused}
    assert runs == {"plain": 1, "up": 2, "down": 2}


def test_a_failed_periodic_checkpoint_is_tried_again(osmo: Osmo, tmp_path: Path) -> None:
    """The first periodic uploads fail (a file stands where the URL's folder goes); once it
    is gone, a later periodic upload lands, which the task itself waits for before exiting."""
    blocker = tmp_path / "ckpts"
    blocker.write_text("a file where the checkpoint folder should go")
    landed = blocker / "run" / "state.txt"
    spec = write(tmp_path / "wf.yaml", f"""
workflow:
  name: ckpt-retry
  tasks:
  - name: fit
    command: [sh, -c, "mkdir -p {{{{output}}}}/ckpt; echo step > {{{{output}}}}/ckpt/state.txt; i=0; while [ ! -e {landed} ]; do i=$((i+1)); [ $i -lt 600 ] || exit 9; sleep 0.05; done"]
    checkpoint:
    - path: "{{{{output}}}}/ckpt"
      url: file://{blocker}/run
      frequency: 1s
""")
    wf = osmo.submit(spec)
    deadline = time.monotonic() + 60
    while "failed (retried next time)" not in osmo("logs", wf, "-t", "fit").out:
        assert time.monotonic() < deadline, "no periodic upload failed"
        time.sleep(0.2)
    blocker.unlink()  # the destination works from now on
    info = osmo.wait_for(wf, ended)
    assert info["status"] == "COMPLETED", (info, osmo("logs", wf).out)
    assert landed.read_text() == "step\n"
    logs = osmo("logs", wf, "-t", "fit").out
    assert logs.index("failed (retried next time)") < logs.index("checkpoint uploaded to")
