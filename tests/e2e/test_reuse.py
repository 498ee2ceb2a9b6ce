"""No surprise from reuse (#31): what runs again by default, what is reused, and how it shows.

The default (docs/how-to/caching.md): a bare command task that feeds no other task runs every time it
is submitted, as in OSMO; typed tasks and tasks whose outputs feed another task of the workflow
reuse an identical earlier success. ``cache: true`` (task or workflow) and ``osmo submit
--reuse`` turn reuse on where the default is off; ``cache: false`` and ``--no-cache`` turn it
off. A reused task says so in ``osmo submit --wait``'s output, and its ``osmo logs`` shows the
log of the attempt it reused under a header that names it.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

from tests.conftest import REPO, Osmo, write

# OSMO's first tutorial (hello_world), as its users type it; the marker counts real runs.
HELLO = """
workflow:
  name: hello_world
  tasks:
  - name: hello
    image: ubuntu:24.04
    command: ["sh", "-c", "echo ran >> {marker}; echo Hello from OSMO!"]
"""


def _hello(tmp_path: Path, extra: str = "") -> Path:
    return write(tmp_path / "hello.yaml", HELLO.format(marker=tmp_path / "ran") + extra)


def _runs(tmp_path: Path) -> int:
    marker = tmp_path / "ran"
    return len(marker.read_text().split()) if marker.exists() else 0


def _submit(osmo: Osmo, spec: Path, *args: str) -> tuple[str, str]:
    """Submit with ``--wait`` (piped, as a script sees it); the workflow id and the output."""
    r = osmo("submit", str(spec), "--wait", *args)
    assert r.code == 0, r.out + r.err
    return r.out.splitlines()[0].split(" - ")[1], r.out


def _tasks(osmo: Osmo, wf_id: str) -> dict[str, dict]:
    return {t["name"]: t for t in osmo.query(wf_id)["tasks"]}


def test_hello_twice_runs_and_prints_both_times(shared_osmo: Osmo, tmp_path: Path) -> None:
    spec = _hello(tmp_path)
    first, _ = _submit(shared_osmo, spec)
    second, out = _submit(shared_osmo, spec)
    assert _runs(tmp_path) == 2
    assert not _tasks(shared_osmo, second)["hello"]["reused"]
    assert "cached" not in out and "reused" not in out.lower()
    logs = shared_osmo("logs", second, check=True).out
    assert "[hello] Hello from OSMO!" in logs and first not in logs


def test_submit_reuse_shows_it_and_the_reused_log(shared_osmo: Osmo, tmp_path: Path) -> None:
    spec = _hello(tmp_path)
    first, _ = _submit(shared_osmo, spec)
    second, out = _submit(shared_osmo, spec, "--reuse")
    assert _runs(tmp_path) == 1  # not run again
    assert _tasks(shared_osmo, second)["hello"]["reused"]
    assert "hello: COMPLETED (cached)" in out
    assert re.search(rf"reused 1 task.* hello \(from {first} task hello retry 0\)", out), out
    logs = shared_osmo("logs", second).out.splitlines()
    header = [i for i, line in enumerate(logs)
              if f"reused: the log of {first} task hello retry 0" in line]
    assert header, logs
    assert logs[header[0]].split(" ", 2)[2].startswith("[hello][osmo] ")
    assert any("[hello] Hello from OSMO!" in line for line in logs[header[0] + 1:]), logs
    # the task's own log, filtered, shows it too; another retry does not
    assert "Hello from OSMO!" in shared_osmo("logs", second, "-t", "hello", "-r", "0").out
    assert "Hello from OSMO!" not in shared_osmo("logs", second, "-t", "hello", "-r", "1").out


def test_cache_true_in_the_spec_reuses(shared_osmo: Osmo, tmp_path: Path) -> None:
    task_level = _hello(tmp_path, "    cache: true\n")
    first, _ = _submit(shared_osmo, task_level)
    second, out = _submit(shared_osmo, task_level)
    assert _runs(tmp_path) == 1 and _tasks(shared_osmo, second)["hello"]["reused"]
    assert "reused 1 task" in out
    workflow_level = write(tmp_path / "wf.yaml", HELLO.format(marker=tmp_path / "ran")
                           .replace("  tasks:", "  cache: true\n  tasks:"))
    _submit(shared_osmo, workflow_level)
    assert _runs(tmp_path) == 1  # the same task: reused from the first run


def test_cache_false_wins_over_reuse_and_no_cache_over_cache_true(shared_osmo: Osmo,
                                                                 tmp_path: Path) -> None:
    off = _hello(tmp_path, "    cache: false\n")
    _submit(shared_osmo, off)
    _submit(shared_osmo, off, "--reuse")
    assert _runs(tmp_path) == 2
    on = _hello(tmp_path, "    cache: true\n")
    _submit(shared_osmo, on)
    assert _runs(tmp_path) == 2  # an identical success exists (cache: false only ran it)
    _submit(shared_osmo, on, "--no-cache")
    assert _runs(tmp_path) == 3
    r = shared_osmo("submit", str(on), "--reuse", "--no-cache")
    assert r.code == 2 and "--reuse" in r.err and "--no-cache" in r.err


PIPELINE = """
workflow:
  name: feeds
  tasks:
  - name: make
    command: ["sh", "-c", "echo make >> {log}; echo 21 > {{{{output}}}}/n"]
  - name: show
    command: ["sh", "-c", "echo show >> {log}; echo $(( $(cat {{{{input:make}}}}/n) * 2 ))"]
    inputs: [{{task: make}}]
"""


def test_a_task_that_feeds_another_is_reused_its_consumer_runs(shared_osmo: Osmo,
                                                                tmp_path: Path) -> None:
    log = tmp_path / "runs.log"
    spec = write(tmp_path / "p.yaml", PIPELINE.format(log=log))
    first, _ = _submit(shared_osmo, spec)
    second, out = _submit(shared_osmo, spec)
    assert sorted(log.read_text().split()) == ["make", "show", "show"]  # make ran once
    tasks = _tasks(shared_osmo, second)
    assert tasks["make"]["reused"] and not tasks["show"]["reused"]
    assert f"make (from {first} task make retry 0)" in out
    assert "[show] 42" in shared_osmo("logs", second, "-t", "show", check=True).out


def test_typed_tasks_are_still_reused(shared_osmo: Osmo, tmp_path: Path) -> None:
    project = tmp_path / "project"
    shutil.copytree(REPO / "examples" / "custom_task", project,
                    ignore=shutil.ignore_patterns("__pycache__"))
    first, _ = _submit(shared_osmo, project / "workflow.yaml")
    second, out = _submit(shared_osmo, project / "workflow.yaml")
    tasks = _tasks(shared_osmo, second)
    assert tasks["numbers"]["reused"] and tasks["cubes"]["reused"]  # cubes feeds nothing
    assert "reused 2 tasks" in out
    logs = shared_osmo("logs", second, "-t", "cubes", check=True).out
    assert f"reused: the log of {first} task cubes retry 0" in logs
    assert "[cubes] sum = 3025" in logs


def test_a_task_restart_reused_shows_the_log_it_reused(shared_osmo: Osmo, tmp_path: Path) -> None:
    gate = tmp_path / "failed-once"
    spec = write(tmp_path / "r.yaml", f"""
workflow:
  name: restarted
  tasks:
  - name: a
    command: ["sh", "-c", "echo made by a; echo 1 > {{{{output}}}}/x"]
  - name: b
    command: ["sh", "-c", "[ -e {gate} ] || {{ touch {gate}; exit 1; }}; echo b ok"]
    inputs: [{{task: a}}]
""")
    r = shared_osmo("submit", str(spec), "--wait")
    assert r.code == 1, r.out + r.err
    first = r.out.splitlines()[0].split(" - ")[1]
    r = shared_osmo("restart", first, "--wait")
    assert r.code == 0, r.out + r.err
    second = r.out.splitlines()[0].split(" - ")[1]
    assert f"a (from {first})" in r.out  # restart's reuse says so too
    logs = shared_osmo("logs", second, "-t", "a", check=True).out
    assert f"reused: the log of {first} task a retry 0 follows" in logs
    assert "[a] made by a" in logs
