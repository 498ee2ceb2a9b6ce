"""OSMO's argument forms through the real CLI and a real server (issue 17, item 1)."""

from __future__ import annotations

import json
from pathlib import Path

from tests.conftest import Osmo, ended, write

SPEC = """
workflow:
  name: hello
  tasks:
  - name: say
    command: [sh, -c, 'echo "{{ greeting }} {{ count }} {{ word }} $A $B"; echo oops >&2']
default-values:
  greeting: hi
  count: 1
  word: none
"""


def test_set_values_as_osmo_takes_them(osmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "hello.yaml", SPEC)
    wf = osmo.submit(spec, "--set", "greeting=hola", "count=3", "--set", "count=4",
                     "--set-string", "word=007", "--set-env", "A=1", "B=2", "--set-env", "A=5",
                     "--wait")
    out = osmo("logs", wf, "-t", "say", check=True).out
    assert "hola 4 007 5 2" in out  # several K=V per flag, flags repeated, later wins


def test_a_swallowed_spec_file_is_named_with_the_fix(osmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "hello.yaml", SPEC)
    r = osmo("submit", "--set", "greeting=hola", "count=3", str(spec))
    assert r.code == 2 and "Traceback" not in r.err
    assert (f"--set takes every K=V after it, and it took '{spec}'. Put the file first: "
            f"osmo submit {spec} --set greeting=hola count=3") in r.err.replace("\n", " ")
    assert osmo.server_pid() is None  # nothing was submitted: no server was even started


def test_global_options_after_the_verb_cancel_several_and_stderr_logs(
        osmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "hello.yaml", SPEC)
    done = osmo.submit(spec, "--wait")
    status = osmo("server", "status", "--format", "json", check=True).json()
    endpoint = status["endpoint"]  # type: ignore[index]

    # --server and --format after the verb, as OSMO users type them
    info = osmo("query", done, "--server", endpoint, "--format", "json", check=True).json()
    assert info["id"] == done and ended(info)  # type: ignore[index]
    assert json.loads(osmo("list", "-t", "json", "--server", endpoint, check=True).out)
    assert json.loads(osmo("-t", "json", "list", check=True).out)

    # logs --error: stderr lines only
    errors = osmo("logs", done, "--error", check=True).out
    assert "oops" in errors and "hi 1" not in errors
    assert "hi 1" in osmo("logs", done, check=True).out

    # cancel takes several ids; one that fails does not stop the others
    sleepy = write(tmp_path / "sleepy.yaml", "workflow:\n  name: sleepy\n  tasks:\n"
                   "  - {name: nap, command: [sleep, '60']}\n")
    first, second = osmo.submit(sleepy), osmo.submit(sleepy)
    r = osmo("cancel", first, "nope-9", second)
    assert r.code == 2, r
    assert f"Workflow {first}: " in r.out and f"Workflow {second}: " in r.out
    assert "nope-9" in r.err and "Traceback" not in r.err
    for wf in (first, second):
        assert osmo.wait_for(wf, ended)["status"] == "FAILED_CANCELED"


def test_args_expand_kubernetes_style_vars(osmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "vars.yaml", """
workflow:
  name: vars
  tasks:
  - name: show
    command: [printf]
    args: ['%s|%s|%s|%s|%s\\n', '$(GREETING)', '$$(GREETING)', '$(OSMO_TASK)', '$(NOPE)',
           '$(WHO)']
    environment:
      GREETING: hello
""")
    wf = osmo.submit(spec, "--set-env", "WHO=osmo", "--wait")
    out = osmo("logs", wf, "-t", "show", check=True).out
    assert "hello|$(GREETING)|show|$(NOPE)|osmo" in out


def test_events_show_the_timeline_after_a_retry(osmo: Osmo, tmp_path: Path) -> None:
    marker = tmp_path / "tried"
    spec = write(tmp_path / "flaky.yaml", f"""
workflow:
  name: flaky
  tasks:
  - name: flaky
    command: [sh, -c, 'if [ -e {marker} ]; then echo ok; else touch {marker}; exit 7; fi']
    exitActions:
      RESCHEDULE: 7
""")
    wf = osmo.submit(spec, "--wait")
    events = osmo("workflow", "events", wf, "--format", "json", check=True).json()
    mine = [(e["retry"], e["status"]) for e in events if e["task"] == "flaky"]  # type: ignore[index]
    # retry 0 ran and failed with 7, was rescheduled as retry 1, which completed
    assert (0, "RUNNING") in mine and (1, "RUNNING") in mine and mine[-1] == (1, "COMPLETED")
    assert mine.index((0, "RUNNING")) < mine.index((1, "RUNNING"))
    retried = [e for e in events if e["task"] == "flaky" and e["retry"] == 0  # type: ignore[index]
               and e["status"] not in ("PENDING", "SCHEDULING", "INITIALIZING", "RUNNING")]
    assert retried and "7" in retried[0]["message"], retried  # why retry 0 ended
    assert all(e["node"] == "local" for e in events  # type: ignore[index]
               if e["task"] and e["status"] == "RUNNING")
    assert [e["status"] for e in events if e["task"] is None][-1] == "COMPLETED"  # type: ignore[index]

    text = osmo("events", wf, "-t", "flaky", check=True).out.splitlines()
    assert any("[flaky retry-1]  RUNNING  on " in line for line in text), text
    assert not any("[workflow]" in line for line in text)
    assert osmo("events", "nope-1").code == 2


def test_labels_filter_and_tags(osmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "lab.yaml", """
workflow:
  name: lab
  labels: {team: perception, stage: dev}
  tasks:
  - {name: a, command: ['true']}
""")
    first = osmo.submit(spec, "--label", "stage=prod", "--label", "run=1", "--wait")
    second = osmo.submit(spec, "--label", "run=2", "--wait")
    info = osmo.query(first)
    assert info["labels"] == {"team": "perception", "stage": "prod", "run": "1"}  # merged

    def listed(*labels: str) -> list[str]:
        args = [a for label in labels for a in ("--label", label)]
        rows = osmo("list", *args, "--format", "json", check=True).json()
        return [r["id"] for r in rows]  # type: ignore[union-attr, index]

    assert listed("team=perception") == [second, first]
    assert listed("stage=prod") == [first]
    assert listed("stage=dev", "run=2") == [second]
    assert listed("stage=prod", "run=2") == []
    assert listed("nope=x") == []
    bad = osmo("list", "--label", "bad key=x")
    assert bad.code == 2 and "label key" in bad.err

    r = osmo("workflow", "tag", first, "--add", "best", "baseline", check=True)
    assert "best" in r.out and "baseline" in r.out
    tags = osmo("workflow", "tag", first, "--remove", "baseline", "--add", "v2",
                "--format", "json", check=True).json()
    assert tags == {"workflow_id": first, "tags": ["best", "v2"]}
    assert osmo.query(first)["tags"] == ["best", "v2"]
    assert osmo.query(second)["tags"] == []
    assert "Tags        : best, v2" in osmo("query", first, check=True).out
    assert osmo("workflow", "tag", first, "--add", "no spaces").code == 2
    assert osmo("workflow", "tag", "nope-1", "--add", "x").code == 2

    # a restart keeps the labels given at submit
    again = osmo("restart", first, check=True).out.split(" - ")[1].strip()
    assert osmo.query(again)["labels"]["stage"] == "prod"


def test_priority_orders_waiting_work(osmo: Osmo, tmp_path: Path) -> None:
    osmo("server", "start", "--cpus", "1", check=True)
    gate = tmp_path / "gate"
    busy = write(tmp_path / "busy.yaml", f"""
workflow:
  name: busy
  resources: {{default: {{cpu: 1}}}}
  tasks:
  - {{name: t, command: [sh, -c, 'while [ ! -e {gate} ]; do sleep 0.05; done']}}
""")
    quick = write(tmp_path / "quick.yaml", """
workflow:
  name: quick
  resources: {default: {cpu: 1}}
  tasks:
  - {name: t, command: ['true']}
""")
    holder = osmo.submit(busy)
    osmo.wait_for(holder, lambda i: i["tasks"][0]["status"] == "RUNNING")
    low = osmo.submit(quick, "--priority", "low")
    normal = osmo.submit(quick)
    high = osmo.submit(quick, "--priority", "HIGH")
    assert osmo.query(high)["priority"] == "HIGH" and osmo.query(normal)["priority"] == "NORMAL"
    gate.touch()
    started = {wf: osmo.wait_for(wf, ended)["tasks"][0]["started_at"]
               for wf in (low, normal, high)}
    assert started[high] < started[normal] < started[low], started
    assert "Priority    : LOW" in osmo("query", low, check=True).out
    assert osmo("submit", str(quick), "--priority", "urgent").code == 2
