"""The runner as the worker runs it: a real ``python -m osmo.tasktypes.runner`` process."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from osmo.record import read_lineage
from tests.conftest import write

TYPES = '''
import time
from osmo import Param, task_type

@task_type(version="5", params={"n": Param(int, default=3), "word": Param(str)})
def write_words(ctx):
    """Write word n times, and a lineage-stamped MCAP."""
    text = (ctx.inputs[0] / "in.txt").read_text() + ctx.input_named["up"].name
    (ctx.output / "words.txt").write_text(text + " " + " ".join([ctx.params["word"]] * ctx.params["n"]))
    ctx.progress(1, 2, "half")
    with ctx.mcap_writer("sub/run.mcap", metadata={"k": "v"}) as mc:
        ch = mc.add_json_channel("/x", "X", {"type": "object"})
        mc.write(ch, {"x": 1})
    ctx.log.info("done")

class Slow:
    """A type whose warm() (what a warm runner does first) takes 0.5 s, its run 0.1 s."""
    name, version, description, params, resources = "slow", "1", "slow", {}, {}

    def warm(self):
        time.sleep(0.5)

    def run(self, ctx):
        time.sleep(0.1)
        print("ran")

slow = Slow()

@task_type(version="1")
def explode(ctx):
    raise ValueError("the sensor is on fire")

@task_type(version="1")
def patient(ctx):
    (ctx.output / "started").write_text("yes")
    while True:
        ctx.check_cancelled()
        time.sleep(0.01)
'''


def _context(tmp_path: Path, type_ref: str, params: dict[str, Any],
             version: str | None = None) -> Path:
    up = tmp_path / "up"
    write(up / "in.txt", "from upstream;")
    (tmp_path / "output.partial").mkdir(exist_ok=True)
    (tmp_path / "work").mkdir(exist_ok=True)
    data = {"format": 1, "type": type_ref, "type_version": version, "paths": [str(tmp_path)],
            "params": params, "inputs": [{"name": "up", "path": str(up)}],
            "output": str(tmp_path / "output.partial"), "workdir": str(tmp_path / "work"),
            "workflow_id": "wf-1", "task": "t", "retry": 0, "attempt_id": "wf-1:t:0"}
    path = tmp_path / "task.json"
    path.write_text(json.dumps(data))
    write(tmp_path / "mytypes.py", TYPES)
    return path


def _env() -> dict[str, str]:
    return dict(os.environ, OSMO_WORKFLOW_ID="wf-1", OSMO_TASK="t", OSMO_RETRY="0")


def _run(context: Path, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "osmo.tasktypes.runner", str(context)],
                          capture_output=True, text=True, timeout=60, env=_env() | env,
                          cwd=context.parent / "work")


def test_success_fills_defaults_and_stamps_lineage(tmp_path: Path) -> None:
    proc = _run(_context(tmp_path, "mytypes:write_words", {"word": "go"}, version="5"))
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "output.partial"
    assert (out / "words.txt").read_text() == "from upstream;up go go go"
    assert proc.stdout.splitlines() == ["[osmo:progress] 1/2 half", "done"]
    lineage = read_lineage(out / "sub" / "run.mcap")
    assert lineage is not None
    assert (lineage.plugin, lineage.attempt_id, lineage.params) == (
        "mytypes:write_words@5", "wf-1:t:0", {"word": "go", "n": 3})


def test_timing_prints_the_run_s_own_seconds_after_its_imports(tmp_path: Path) -> None:
    """``OSMO_TASK_TIMING=1``: one compute line, the run alone (warm()'s 0.5 s not in it)."""
    context = _context(tmp_path, "mytypes:slow", {})
    proc = _run(context, OSMO_TASK_TIMING="1")
    assert proc.returncode == 0, proc.stderr
    ran, line = proc.stdout.splitlines()
    assert ran == "ran" and line.startswith("osmo: compute "), proc.stdout
    assert 0.1 <= float(line.split()[-1]) < 0.5, line
    untimed = _run(context)
    assert untimed.returncode == 0 and untimed.stdout.splitlines() == ["ran"], untimed.stdout


def test_exception_exits_1_with_traceback(tmp_path: Path) -> None:
    proc = _run(_context(tmp_path, "mytypes:explode", {}))
    assert proc.returncode == 1
    assert "Traceback" in proc.stderr and "ValueError: the sensor is on fire" in proc.stderr


def test_version_changed_since_submit_is_refused(tmp_path: Path) -> None:
    proc = _run(_context(tmp_path, "mytypes:write_words", {"word": "go"}, version="4"))
    assert proc.returncode == 1
    assert "is version 5 here, but the workflow was submitted against version 4" in proc.stderr
    assert not (tmp_path / "output.partial" / "words.txt").exists()


def test_unknown_type_exits_1_with_the_reason(tmp_path: Path) -> None:
    proc = _run(_context(tmp_path, "mytypes:nothing", {}))
    assert proc.returncode == 1
    assert "module 'mytypes' has no attribute 'nothing'" in proc.stderr


def test_sigterm_cancels_with_143(tmp_path: Path) -> None:
    context = _context(tmp_path, "mytypes:patient", {})
    proc = subprocess.Popen([sys.executable, "-m", "osmo.tasktypes.runner", str(context)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=_env())
    started = tmp_path / "output.partial" / "started"
    deadline = time.monotonic() + 60
    while not started.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "the task never started"
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143
    assert "stopped: task 't' was asked to stop" in err


KEPT = """
import sys
from pathlib import Path
from osmo.tasktypes import runner
sys.path.insert(0, {folder!r})  # where a warm runner puts the type's folders
import mytypes
runner.keep_resolved("mytypes:explode", mytypes.slow)  # a stand-in that shows it is taken
if {moved}:
    sys.path.append({folder!r} + "/elsewhere")  # not the path it was resolved on
sys.exit(runner.run_context_file(Path({context!r})))
"""


def test_a_kept_resolution_is_taken_only_on_the_path_it_was_made_on(tmp_path: Path) -> None:
    """A warm runner's fork takes the type its runner resolved, not a fresh entry-point scan;
    with another ``sys.path`` it resolves the type again."""
    context = _context(tmp_path, "mytypes:explode", {})
    for moved, code, seen in ((False, 0, "ran"), (True, 1, "the sensor is on fire")):
        script = KEPT.format(folder=str(tmp_path), moved=moved, context=str(context))
        proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                              timeout=60, env=_env(), cwd=tmp_path / "work")
        assert proc.returncode == code, proc.stderr
        assert seen in proc.stdout + proc.stderr
