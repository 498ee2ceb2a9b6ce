"""Task ``credentials:`` end to end through the real CLI: checks at submit, injection, masking.

The secret values must appear nowhere in OSMO_HOME but the credentials table of the store:
not in logs, the run record, the spec, lineage or any other table, and not in the attempt's
folder once the attempt has ended (mounted files are deleted).
"""

from __future__ import annotations

import hashlib
import sqlite3
import time
from pathlib import Path

from osmo.server.cache import fingerprint
from osmo.spec.model import TaskSpec
from tests.conftest import Osmo, write

TOKEN = "tok-9f8e7d6c5b4a"
KEY = "ssh-key-Z1Y2X3W4"

WORKFLOW = """
workflow:
  name: secrets
  tasks:
  - name: use
    command: [sh, -c, 'echo "token is $API_TOKEN"; cat /etc/keys/id_key; echo;
      printf %s "$API_TOKEN" | sha256sum | cut -c1-64 > {{output}}/token.sha256;
      sha256sum < /etc/keys/id_key | cut -c1-64 > {{output}}/key.sha256;
      stat -c %a /etc/keys/id_key > {{output}}/mode']
    credentials:
      api: {API_TOKEN: token}
      ssh: /etc/keys
  - name: plain
    command: [sh, -c, 'echo "[${API_TOKEN-unset}]" | tee {{output}}/env']
"""


def sha(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def where_secrets_are(home: Path) -> dict[str, set[str]]:
    """Secret → files of OSMO_HOME holding it (SQLite files: outside the credentials table)."""
    found: dict[str, set[str]] = {TOKEN: set(), KEY: set()}
    for path in home.rglob("*"):
        if path.is_file() and not path.name.startswith("state.db"):
            data = path.read_bytes()
            for secret in found:
                if secret.encode() in data:
                    found[secret].add(str(path.relative_to(home)))
    db = sqlite3.connect(home / "state.db")
    try:
        tables = [r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")]
        for table in tables:
            rows = repr(db.execute(f"SELECT * FROM {table}").fetchall())  # noqa: S608
            for secret in found:
                if secret in rows:
                    found[secret].add(f"state.db:{table}")
    finally:
        db.close()
    return found


def test_a_task_gets_its_secrets_and_nothing_shows_them(osmo: Osmo, tmp_path: Path) -> None:
    osmo("credential", "set", "api", "--payload", f"token={TOKEN}", "--payload", "user=robot",
         check=True)
    osmo("credential", "set", "ssh", "--payload", f"id_key={KEY}", check=True)
    r = osmo("submit", str(write(tmp_path / "wf.yaml", WORKFLOW)), "--wait")
    wf_id = r.out.splitlines()[0].split(" - ")[1]
    info = osmo.query(wf_id)
    assert r.code == 0 and info["status"] == "COMPLETED", (r, info)
    tasks = {t["name"]: t for t in info["tasks"]}
    out = Path(tasks["use"]["output"])
    assert (out / "token.sha256").read_text().strip() == sha(TOKEN)  # the right values
    assert (out / "key.sha256").read_text().strip() == sha(KEY)
    assert (out / "mode").read_text().strip() == "600"
    assert (Path(tasks["plain"]["output"]) / "env").read_text() == "[unset]\n"

    logs = osmo("logs", wf_id, check=True).out
    assert "[use] token is ****" in logs and "[use] ****" in logs
    assert "[plain] [unset]" in logs
    followed = osmo("logs", wf_id, "-f", check=True).out
    assert "[use] token is ****" in followed
    shown = logs + followed + osmo("query", wf_id, "-v", check=True).out
    shown += osmo("spec", wf_id, check=True).out + osmo("credential", "list", check=True).out
    assert TOKEN not in shown and KEY not in shown

    deadline = time.monotonic() + 30
    while not (osmo.home / "runs" / wf_id / "run.mcap").exists():
        assert time.monotonic() < deadline, "no run record"
        time.sleep(0.1)
    osmo.stop_server()
    assert list(osmo.home.glob(f"runs/{wf_id}/use/0/log.txt"))  # what is scanned is there
    assert where_secrets_are(osmo.home) == {TOKEN: {"state.db:credentials"},
                                            KEY: {"state.db:credentials"}}


def test_submit_names_every_missing_credential_and_key(osmo: Osmo, tmp_path: Path) -> None:
    osmo("credential", "set", "db", "--payload", "user=u", "--payload", "password=p", check=True)
    spec = write(tmp_path / "wf.yaml", """
workflow:
  name: missing
  tasks:
  - name: a
    command: [env]
    environment: {PW: x}
    credentials:
      db: {PW: pass, USER: user}
      api: {TOKEN: token}
  - name: b
    command: [env]
    credentials:
      api: /etc/api
      ssh: /etc/ssh
""")
    r = osmo("submit", str(spec))
    assert r.code == 2 and r.out == ""
    assert r.err == (
        "error: cannot use the credentials of this workflow:\n"
        "  credential 'api' (used by task 'a', 'b') does not exist; store it with "
        "`osmo credential set api --payload KEY=VALUE ...`\n"
        "  credential 'ssh' (used by task 'b') does not exist; store it with "
        "`osmo credential set ssh --payload KEY=VALUE ...`\n"
        "  task 'a': credential 'db' has no key 'pass' (for $PW); its keys: password, user\n"
        "  task 'a': $PW is set by both 'environment' and credential 'db'; keep one\n")
    assert osmo("list", "--format", "json", check=True).json() == []


CHAINED = """
workflow:
  name: later
  tasks:
  - name: first
    command: [sh, -c, 'while [ ! -e RELEASE ]; do sleep 0.05; done']
  - name: second
    command: [sh, -c, 'echo "$TOKEN"']
    inputs:
    - task: first
    credentials:
      api: {TOKEN: token}
"""


def test_credential_deleted_after_submit_fails_the_start(osmo: Osmo, tmp_path: Path) -> None:
    osmo("credential", "set", "api", "--payload", f"token={TOKEN}", check=True)
    release = tmp_path / "release"
    wf_id = osmo.submit(write(tmp_path / "wf.yaml", CHAINED.replace("RELEASE", str(release))))
    osmo("credential", "delete", "api", check=True)
    release.touch()
    info = osmo.wait_for(wf_id, lambda i: i["status"] not in ("PENDING", "RUNNING"))
    second = [t for t in info["tasks"] if t["name"] == "second"][0]
    assert second["status"] == "FAILED_START_ERROR", info
    assert second["message"] == (
        "task 'second': credential 'api' does not exist (deleted after the workflow was "
        "submitted?); store it again with `osmo credential set api --payload KEY=VALUE ...`")


def test_cache_fingerprint_holds_credential_names_only() -> None:
    plain = TaskSpec(name="t", command=("env",))
    used = TaskSpec(name="t", command=("env",), credentials={"api": {"TOKEN": "token"}})
    other = TaskSpec(name="t", command=("env",), credentials={"api": {"TOKEN": "other"}})
    keys = {fingerprint(t, []) for t in (plain, used, other)}
    assert len(keys) == 3  # which secret a task uses is part of its definition
    assert fingerprint(plain, []) == (  # tasks without credentials keep their fingerprints
        "sha256:" + hashlib.sha256(b'{"args":[],"command":["env"],"environment":[],"files":[],'
                                   b'"image":null,"inputs":[],"params":{},"type":null,"v":1}'
                                   ).hexdigest())
