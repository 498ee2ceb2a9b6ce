"""Typed tasks end to end: YAML and builder through the real CLI/SDK and a real server."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from tests.conftest import REPO, Osmo, write
from tests.tasktypes.conftest import write_dist

EXAMPLE = REPO / "examples" / "custom_task"


def _copy_example(tmp_path: Path) -> Path:
    folder = tmp_path / "project"
    shutil.copytree(EXAMPLE, folder, ignore=shutil.ignore_patterns("__pycache__"))
    return folder


def _tasks(osmo: Osmo, wf_id: str) -> dict[str, dict]:
    return {t["name"]: t for t in osmo.query(wf_id)["tasks"]}


def test_yaml_custom_type_runs_and_caches_by_version(shared_osmo: Osmo, tmp_path: Path) -> None:
    project = _copy_example(tmp_path)
    spec = project / "workflow.yaml"
    first = shared_osmo.submit(spec, "--wait")
    tasks = _tasks(shared_osmo, first)
    assert {t["status"] for t in tasks.values()} == {"COMPLETED"}
    powers = Path(tasks["cubes"]["output"]) / "powers.txt"
    assert powers.read_text().split() == [str(n ** 3) for n in range(1, 11)]
    logs = shared_osmo("logs", first, "-t", "cubes", check=True).out
    assert "[cubes] [osmo:progress] 10/10" in logs and "[cubes] sum = 3025" in logs
    lineage = shared_osmo("lineage", f"{first}:cubes", "--format", "json", check=True).json()
    plugins = {n["task"]: n["plugin"] for n in lineage["nodes"].values()}  # type: ignore[index]
    assert plugins == {"cubes": "tasks:power@2", "numbers": "tasks:numbers@1"}

    again = _tasks(shared_osmo, shared_osmo.submit(spec, "--wait"))
    assert again["cubes"]["reused"] and again["numbers"]["reused"]

    tasks_py = project / "tasks.py"  # a new version of one type: only its task reruns
    text = tasks_py.read_text().replace('version = "2"', 'version = "3"')
    tasks_py.write_text(text.replace('f"{p}\\n"', 'f"{p} \\n"'))  # (new content: new lineage)
    third = shared_osmo.submit(spec, "--wait")
    after = _tasks(shared_osmo, third)
    assert after["numbers"]["reused"] and not after["cubes"]["reused"]
    assert after["cubes"]["status"] == "COMPLETED"
    lineage = shared_osmo("lineage", f"{third}:cubes", check=True).out
    assert "tasks:power@3" in lineage.splitlines()[0]


def test_a_type_in_a_folder_the_task_cannot_read_says_so(shared_osmo: Osmo,
                                                       tmp_path: Path) -> None:
    """A root server runs its tasks as nobody: a 0700 project folder is there but shut."""
    if os.geteuid() != 0:
        return  # tasks run as the invoking user, who can read their own project
    project = _copy_example(tmp_path)
    project.chmod(0o700)
    wf = shared_osmo("submit", str(project / "workflow.yaml"), "--wait", "--no-cache")
    assert wf.code == 1, wf
    wf_id = wf.out.splitlines()[0].split(" - ")[1]
    logs = shared_osmo("logs", wf_id, check=True).out
    assert f"this task cannot read {project}" in logs and "chmod o+rx" in logs, logs


def test_builder_example_runs_through_the_sdk(shared_osmo: Osmo) -> None:
    proc = subprocess.run([sys.executable, str(EXAMPLE / "build.py")], env=shared_osmo.env,
                          cwd=REPO, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.splitlines() == ["COMPLETED", "sum of cubes = 3025"]


def test_bad_params_are_rejected_at_submit_with_positions(shared_osmo: Osmo,
                                                          tmp_path: Path) -> None:
    project = _copy_example(tmp_path)
    spec = write(project / "bad.yaml", """workflow:
  name: bad-params
  tasks:
  - name: numbers
    type: tasks:numbers
    params: {count: 0, strat: 2}
  - name: other
    type: tasks:nope
""")
    for verb in ("submit", "validate"):
        r = shared_osmo(verb, str(spec))
        assert r.code == 2, r.out + r.err
        assert f"{spec}:6:21: param 'count' of task 'numbers' must be at least 1; got 0" in r.err
        assert (f"{spec}:6:24: task 'numbers': unknown param 'strat' for type 'tasks:numbers' "
                "(did you mean 'start'?)") in r.err
        assert f"{spec}:8:11: task 'other': task type 'tasks:nope'" in r.err
    assert "bad-params" not in shared_osmo("list", check=True).out


def test_cancel_stops_a_typed_task_through_its_context(shared_osmo: Osmo,
                                                       tmp_path: Path) -> None:
    marker = tmp_path / "started"
    write(tmp_path / "slow.py", f"""
import time
from osmo import task_type

@task_type(version="1")
def wait(ctx):
    open({str(marker)!r}, "w").close()
    while True:
        ctx.check_cancelled()
        time.sleep(0.02)
""")
    spec = write(tmp_path / "wf.yaml", """workflow:
  name: typed-cancel
  tasks:
  - name: slow
    type: slow:wait
""")
    wf_id = shared_osmo.submit(spec)
    shared_osmo.wait_for(wf_id, lambda _info: marker.exists())
    shared_osmo("cancel", wf_id, check=True)
    info = shared_osmo.wait_for(wf_id, lambda i: i["status"].startswith("FAILED"))
    assert info["tasks"][0]["status"] == "FAILED_CANCELED"
    logs = shared_osmo("logs", wf_id, check=True).out
    assert "stopped: task 'slow' was asked to stop" in logs
    assert "SIGKILL" not in logs  # it stopped within the grace period, by itself


def test_query_shows_a_running_typed_tasks_progress(shared_osmo: Osmo, tmp_path: Path) -> None:
    go = tmp_path / "go"
    write(tmp_path / "steps.py", f"""
import os, time
from osmo import task_type

@task_type(version="1")
def steps(ctx):
    ctx.progress(1, 4, "warming up")
    ctx.progress(2, 4, "rolling out")
    for _ in range(600):
        if os.path.exists({str(go)!r}):
            break
        time.sleep(0.05)
""")
    spec = write(tmp_path / "wf.yaml", """workflow:
  name: typed-progress
  tasks:
  - name: roll
    type: steps:steps
""")
    wf_id = shared_osmo.submit(spec)
    info = shared_osmo.wait_for(wf_id, lambda i: i["tasks"][0].get("progress") is not None)
    assert info["tasks"][0]["progress"] == "2/4 rolling out"
    text = shared_osmo("query", wf_id, check=True).out
    assert "Progress" in text and "2/4 rolling out" in text
    go.touch()
    done = shared_osmo.wait_for(wf_id, lambda i: i["status"] == "COMPLETED")
    assert done["tasks"][0]["progress"] is None  # only running tasks report progress


def test_plugins_list_shows_installed_and_broken_types(tmp_path: Path) -> None:
    site = tmp_path / "site"
    write(site / "fine_plugin.py", """
from osmo import Param, task_type

@task_type(name="demo.fine", version="1.2", params={"n": Param(int, default=3, help="count")})
def FINE(ctx):
    \"\"\"A type that loads.\"\"\"
""")
    write(site / "sim_broken.py", "import mujoco_is_not_here\nROLL = None\n")
    write_dist(site, "demo-plugins", {"demo.fine": "fine_plugin:FINE",
                                      "sim.broken": "sim_broken:ROLL [sim]"})
    osmo = Osmo(tmp_path / "home")  # no server is needed (or started)
    osmo.env["PYTHONPATH"] = os.pathsep.join([str(site), osmo.env.get("PYTHONPATH", "")])
    text = osmo("plugins", "list", "-v", check=True).out
    assert "demo.fine" in text and "1.2" in text and "A type that loads." in text
    assert "n: int (default 3) - count" in text
    assert "BROKEN: task type 'sim.broken' needs module 'mujoco_is_not_here'" in text
    rows = {r["name"]: r for r in json.loads(osmo("plugins", "list", "--format", "json",
                                                  check=True).out)}
    assert rows["sim.broken"]["extra"] == "sim"
    assert rows["sim.broken"]["error"].endswith('pip install "osmo[sim]"')
    assert rows["demo.fine"]["params"]["n"]["default"] == 3
    assert not (tmp_path / "home" / "server.json").exists()


def test_typed_task_survives_server_kill9(osmo: Osmo, tmp_path: Path) -> None:
    started, release = tmp_path / "started", tmp_path / "release"
    write(tmp_path / "slowtypes.py", f"""
import os, time
from osmo import task_type

@task_type(version="7")
def wait(ctx):
    open({str(started)!r}, "w").write(str(os.getpid()))
    while not os.path.exists({str(release)!r}):
        time.sleep(0.02)
    (ctx.output / "done.txt").write_text("done")
""")
    spec = write(tmp_path / "wf.yaml", """workflow:
  name: typed-survive
  tasks:
  - name: slow
    type: slowtypes:wait
""")
    wf_id = osmo.submit(spec)
    osmo.wait_for(wf_id, lambda _info: started.exists())
    server = osmo.server_pid()
    assert server is not None
    os.kill(server, signal.SIGKILL)
    deadline = time.monotonic() + 30
    while _alive(server):
        assert time.monotonic() < deadline
        time.sleep(0.05)
    started.unlink()
    osmo("query", wf_id, check=True)  # a new server restores the workflow from the store
    osmo.wait_for(wf_id, lambda _info: started.exists())
    release.write_text("go")
    info = osmo.wait_for(wf_id, lambda i: i["status"] not in ("PENDING", "RUNNING", "WAITING"))
    assert info["status"] == "COMPLETED", info
    assert info["tasks"][0]["retry"] == 1
    lineage = osmo("lineage", f"{wf_id}:slow", "--format", "json", check=True).json()
    assert [n["plugin"] for n in lineage["nodes"].values()] == ["slowtypes:wait@7"]  # type: ignore[index]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_tasks_wait_passively_unless_their_spec_says_otherwise(shared_osmo: Osmo,
                                                                tmp_path: Path) -> None:
    """OpenMP's idle threads do not spin (``OMP_WAIT_POLICY=PASSIVE``, osmo's default in every
    task's base environment, a typed task's included); a spec's ``environment`` wins."""
    write(tmp_path / "omptypes.py", """
import os
from osmo import task_type

@task_type(version="1")
def policy(ctx):
    (ctx.output / "v").write_text(os.environ.get("OMP_WAIT_POLICY", "unset"))
""")
    spec = write(tmp_path / "omp.yaml", """
workflow:
  name: omp
  tasks:
  - name: plain
    command: [sh, -c, 'printf %s "${OMP_WAIT_POLICY-unset}" > {{output}}/v']
  - name: spins
    command: [sh, -c, 'printf %s "${OMP_WAIT_POLICY-unset}" > {{output}}/v']
    environment: {OMP_WAIT_POLICY: ACTIVE}
  - name: typed
    type: omptypes:policy
""")
    tasks = _tasks(shared_osmo, shared_osmo.submit(spec, "--wait"))
    seen = {name: (Path(t["output"]) / "v").read_text() for name, t in tasks.items()}
    assert seen == {"plain": "PASSIVE", "spins": "ACTIVE", "typed": "PASSIVE"}, tasks


def test_a_task_s_cpu_request_is_its_thread_count(shared_osmo: Osmo, tmp_path: Path) -> None:
    """``OMP_NUM_THREADS`` is the task's cpu request (its resource's, or its type's, which a
    warm runner imports with), as Ray sets it from ``num_cpus``; a spec's ``environment``
    wins, and a task that requests nothing gets none."""
    write(tmp_path / "thrtypes.py", """
import os
from osmo import task_type

@task_type(version="1", resources={"cpu": 2})
def two(ctx):
    (ctx.output / "v").write_text(os.environ.get("OMP_NUM_THREADS", "unset"))
""")
    show = """command: [sh, -c, 'printf %s "${OMP_NUM_THREADS-unset}" > {{output}}/v']"""
    spec = write(tmp_path / "threads.yaml", f"""
workflow:
  name: threads
  resources:
    default: {{cpu: 1}}
    two: {{cpu: 2}}
  tasks:
  - name: one
    {show}
  - name: two
    resource: two
    {show}
  - name: own
    resource: two
    environment: {{OMP_NUM_THREADS: "5"}}
    {show}
  - name: typed
    type: thrtypes:two
""")
    bare = write(tmp_path / "bare.yaml", f"""
workflow:
  name: bare
  tasks:
  - name: none
    {show}
""")
    seen = {}
    for path in (spec, bare):
        tasks = _tasks(shared_osmo, shared_osmo.submit(path, "--wait"))
        seen.update({name: (Path(t["output"]) / "v").read_text() for name, t in tasks.items()})
    assert seen == {"one": "1", "two": "2", "own": "5", "typed": "2", "none": "unset"}, seen
