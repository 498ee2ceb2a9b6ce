"""Image tasks through ``osmo submit`` on a server with ``--runtime container`` (real podman).

Each test checks afterwards that no container or network of its server is left.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from osmo.runtime.container import ContainerEngine
from tests.conftest import Osmo, ended, write
from tests.containers.submitting import (
    container_osmo,
    leftovers,
    lineage_of,
    osmo_lines,
    owner_labels,
    submitted_id,
    task_lines,
    tasks,
)


def submit_wait(osmo: Osmo, spec: Path, *args: str) -> tuple[int, str]:
    r = osmo("submit", str(spec), "--wait", *args, timeout=300)
    return r.code, submitted_id(r.out)


def wait_running_container(engine: ContainerEngine, labels: dict[str, str],
                           timeout: float = 60) -> str:
    deadline = time.monotonic() + timeout
    while not (found := engine.running(labels)):
        assert time.monotonic() < deadline, "no container started"
        time.sleep(0.1)
    return found[0]


def test_data_layout_inputs_files_and_environment(cosmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "layout.yaml", """
workflow:
  name: layout
  tasks:
  - name: make
    image: alpine:3.18
    command: [sh, -c, "echo made > {{output}}/data.txt; id -u > {{output}}/uid"]
  - name: use
    image: alpine:3.18
    command: [sh, /opt/run.sh]
    environment: {GREETING: hi}
    inputs: [{task: make}]
    files:
    - path: /opt/run.sh
      contents: |
        set -e
        echo "by index: $(cat {{input:0}}/data.txt) at {{input:0}}"
        echo "by name: $(cat {{input:make}}/data.txt) at {{input:make}}"
        echo "output: {{output}} $OSMO_OUTPUT"
        echo "env: $GREETING $OSMO_TASK"
        cat conf/settings.txt; echo
        touch {{input:0}}/x 2>/dev/null && echo "input writable" || echo "input read-only"
        (echo changed > /opt/run.sh) 2>/dev/null && echo "file writable" || echo "file read-only"
        echo used > {{output}}/used.txt
    - path: conf/settings.txt
      contents: relative file in the working folder
""")
    code, wf = submit_wait(cosmo, spec)
    lines = task_lines(cosmo, wf)
    assert code == 0, lines
    assert lines["use"] == [
        "by index: made at /osmo/data/input/0", "by name: made at /osmo/data/input/0",
        "output: /osmo/data/output /osmo/data/output", "env: hi use",
        "relative file in the working folder", "input read-only", "file read-only"]
    rows = tasks(cosmo, wf)
    assert (Path(rows["use"]["output"]) / "used.txt").read_text() == "used\n"
    made = Path(rows["make"]["output"])
    assert (made / "uid").read_text().strip() == str(os.getuid())  # the invoking user
    assert made.stat().st_uid == os.getuid()
    image = [ln for ln in osmo_lines(cosmo, wf, "use") if ln.startswith("image ")]
    assert image and "is sha256:" in image[0]


def test_a_secret_is_not_in_inspect_but_the_task_has_it(cosmo: Osmo, engine: ContainerEngine,
                                                        tmp_path: Path) -> None:
    secret = f"s3cr3t-{uuid.uuid4().hex}"
    cosmo("credential", "set", "api", "--payload", f"token={secret}", check=True)
    spec = write(tmp_path / "secret.yaml", """
workflow:
  name: secret
  tasks:
  - name: use
    image: alpine:3.18
    credentials: {api: {API_TOKEN: token}}
    command: [sh, -c, 'printf %s "$API_TOKEN" | md5sum; sleep 30']
""")
    wf = cosmo.submit(spec)
    ident = wait_running_container(engine, {**owner_labels(cosmo), "osmo.workflow": wf})
    inspect = engine.call("container", "inspect", ident)
    i = inspect.find(secret)
    assert i < 0, inspect[max(0, i - 1500):i + 200]
    assert '"API_TOKEN=' not in inspect
    assert json.loads(inspect)[0]["Config"]["Labels"]["osmo.task"] == "use"
    cosmo("cancel", wf, check=True)
    info = cosmo.wait_for(wf, ended)
    assert secret not in json.dumps(info)
    logs = cosmo("logs", wf, check=True).out
    assert hashlib.md5(secret.encode()).hexdigest() in logs and secret not in logs


def test_cancel_and_exec_timeout_stop_the_container(cosmo: Osmo, engine: ContainerEngine,
                                                    tmp_path: Path) -> None:
    spec = write(tmp_path / "long.yaml", """
workflow:
  name: long
  tasks:
  - name: sleeper
    image: alpine:3.18
    command: [sleep, "300"]
""")
    wf = cosmo.submit(spec)
    labels = {**owner_labels(cosmo), "osmo.workflow": wf}
    wait_running_container(engine, labels)
    cosmo("cancel", wf, check=True)
    info = cosmo.wait_for(wf, ended, timeout=60)
    assert info["status"] != "COMPLETED"
    assert leftovers(engine, labels) == ([], [])

    timed = write(tmp_path / "timed.yaml", """
workflow:
  name: timed
  timeout: {exec_timeout: 3s}
  tasks:
  - name: sleeper
    image: alpine:3.18
    command: [sleep, "300"]
""")
    started = time.monotonic()
    code, wf = submit_wait(cosmo, timed)
    assert code == 1 and time.monotonic() - started < 60
    assert tasks(cosmo, wf)["sleeper"]["status"] == "FAILED_EXEC_TIMEOUT"
    assert leftovers(engine, {**owner_labels(cosmo), "osmo.workflow": wf}) == ([], [])


def test_a_missing_image_fails_with_its_name_and_no_password(cosmo: Osmo, tmp_path: Path) -> None:
    password = f"pw-{uuid.uuid4().hex}"
    cosmo("credential", "set", "registry://registry.invalid", "--payload", "username=me",
          "--payload", f"password={password}", check=True)
    spec = write(tmp_path / "missing.yaml", """
workflow:
  name: missing
  tasks:
  - name: pulled
    image: registry.invalid/osmo/nothing:1
    command: ["true"]
""")
    code, wf = submit_wait(cosmo, spec)
    assert code == 1
    row = tasks(cosmo, wf)["pulled"]
    assert row["status"] == "FAILED_START_ERROR"
    assert "image 'registry.invalid/osmo/nothing:1' not found:" in row["message"]
    everything = json.dumps(cosmo.query(wf)) + cosmo("logs", wf).out
    everything += (cosmo.home / "server.log").read_text()
    assert password not in everything


def test_image_id_in_lineage_and_cache_key_a_retag_reruns(
        cosmo: Osmo, images: dict[str, str], engine: ContainerEngine, tmp_path: Path) -> None:
    tag = f"localhost/osmo-test-retag/{uuid.uuid4().hex[:12]}:1"
    first, second = images["alpine:3.18"], images["ubuntu:24.04"]
    assert first != second
    spec = write(tmp_path / "cached.yaml", f"""
workflow:
  name: cached
  tasks:
  - name: once
    image: {tag}
    cache: true
    command: [sh, -c, "echo ran; echo {{{{uuid}}}} > {{{{output}}}}/out.txt"]
""")
    engine.call("tag", first, tag)
    try:
        code, wf1 = submit_wait(cosmo, spec)
        assert code == 0
        assert lineage_of(cosmo, f"{wf1}:once")["image_id"] == first
        code, wf2 = submit_wait(cosmo, spec)
        assert code == 0 and tasks(cosmo, wf2)["once"]["message"].startswith("cached:")
        engine.call("tag", second, tag)  # the same name, another image
        code, wf3 = submit_wait(cosmo, spec)
        assert code == 0 and not tasks(cosmo, wf3)["once"]["message"].startswith("cached:")
        assert task_lines(cosmo, wf3)["once"] == ["ran"]
        assert lineage_of(cosmo, f"{wf3}:once")["image_id"] == second
    finally:
        engine.call("untag", tag, tag)  # only this name (no name: every name of it)


def test_a_typed_task_runs_in_its_image_on_its_python_and_is_reused(
        cosmo: Osmo, python_image: str, engine: ContainerEngine, tmp_path: Path) -> None:
    """A typed task that names an image runs osmo's runner on that image's python3, with its
    params, inputs and output where the image shows them, osmo's code read-only; its
    placement fingerprints the image's id, so the same spec is reused.

    Its type's folder (the workflow's) holds osmo's home here, as a project folder holding
    ``~/.osmo`` would: the task is shown the folder, and an empty folder where the home is."""
    write(tmp_path / "imgtypes.py", """
import json, os, sys
from osmo import Param, task_type

@task_type(version="1", params={"word": Param(str)})
def make(ctx):
    try:
        open("/osmo/lib/osmo/planted.py", "w").write("x")
        code = "osmo's code writable"
    except OSError as exc:
        code = f"osmo's code: {exc.strerror}"
    (ctx.output / "out.json").write_text(json.dumps({
        "word": ctx.params["word"], "container": os.environ.get("container"),
        "python": sys.executable, "output": str(ctx.output), "workdir": os.getcwd(),
        "code": code, "home": sorted(os.listdir("/osmo/types/0/" + os.environ["HOME_IN_TYPES"])),
    }))

@task_type(version="1")
def use(ctx):
    made = json.loads((ctx.input_named["make"] / "out.json").read_text())
    (ctx.output / "used.txt").write_text(f"{made['word']} from {ctx.inputs[0]}")
""")
    spec = write(tmp_path / "typed.yaml", f"""
workflow:
  name: typed-image
  tasks:
  - name: make
    type: imgtypes:make
    image: {python_image}
    params: {{word: hello}}
    environment: {{HOME_IN_TYPES: "{cosmo.home.relative_to(tmp_path)}"}}
  - name: use
    type: imgtypes:use
    image: {python_image}
    inputs: [{{task: make}}]
""")
    code, first = submit_wait(cosmo, spec)
    assert code == 0, (tasks(cosmo, first), task_lines(cosmo, first))
    run = Path(cosmo.home) / "runs" / first
    made = json.loads(next(run.glob("make/*/output/out.json")).read_text())
    assert made == {"word": "hello", "container": "podman", "python": made["python"],
                    "output": "/osmo/data/output", "workdir": "/osmo/run/work",
                    "code": "osmo's code: Read-only file system", "home": []}, made
    assert made["python"].startswith(("/usr/", "/bin/")), made  # the image's interpreter
    used = next(run.glob("use/*/output/used.txt")).read_text()
    assert used == "hello from /osmo/data/input/0"
    image_id = engine.call("image", "inspect", "--format", "{{.Id}}", python_image).strip()
    assert lineage_of(cosmo, f"{first}:make")["image_id"].removeprefix("sha256:") == image_id
    assert any("runs on its python3" in line for line in osmo_lines(cosmo, first, "make"))
    code, again = submit_wait(cosmo, spec)
    assert code == 0 and tasks(cosmo, again)["make"]["message"].startswith("cached:"), \
        tasks(cosmo, again)["make"]


def test_a_typed_task_whose_image_lacks_its_libraries_fails_saying_what_is_missing(
        cosmo: Osmo, python_image: str, tmp_path: Path) -> None:
    """An installed type (found by its entry point: the image has osmo's code, not its
    metadata) in an image without its libraries fails with the import error, not a hang."""
    spec = write(tmp_path / "rollout.yaml", f"""
workflow:
  name: rollout-in-image
  tasks:
  - name: roll
    type: sim.rollout
    image: {python_image}
""")
    code, wf = submit_wait(cosmo, spec)
    assert code != 0
    row = tasks(cosmo, wf)["roll"]
    assert row["status"] == "FAILED", row
    text = "\n".join(task_lines(cosmo, wf).get("roll", []))
    assert text.endswith(f"osmo: task type 'sim.rollout' needs the module 'numpy', which its "
                         f"image '{python_image}' does not have; install it there"), text


def test_orphans_are_removed_after_a_server_kill_9(cosmo: Osmo, engine: ContainerEngine,
                                                   tmp_path: Path) -> None:
    spec = write(tmp_path / "group.yaml", """
workflow:
  name: orphans
  groups:
  - name: pair
    tasks:
    - name: lead
      lead: true
      image: alpine:3.18
      command: [sh, -c, "sleep 8; echo lead done > {{output}}/done.txt"]
    - name: peer
      image: alpine:3.18
      command: [sleep, "300"]
""")
    cosmo("server", "start", "--cpus", "4", check=True)
    wf = cosmo.submit(spec)
    labels = {**owner_labels(cosmo), "osmo.workflow": wf}
    deadline = time.monotonic() + 60
    while len(engine.running(labels)) < 2:
        assert time.monotonic() < deadline, "the group's containers never ran"
        time.sleep(0.1)
    assert engine.networks(owner_labels(cosmo))
    pid = cosmo.server_pid()
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    time.sleep(0.5)
    assert engine.containers(labels), "the containers outlive the server (nothing else kills)"
    cosmo("server", "start", "--cpus", "4", check=True)  # removes them before anything runs
    info = cosmo.wait_for(wf, ended, timeout=120)
    assert info["status"] == "COMPLETED", info
    assert (Path(tasks(cosmo, wf)["lead"]["output"]) / "done.txt").read_text() == "lead done\n"


def test_runtime_container_without_an_engine_names_the_package(tmp_path: Path) -> None:
    empty = tmp_path / "bin"
    empty.mkdir()
    env = dict(os.environ, PATH=str(empty), OSMO_HOME=str(tmp_path / "home"))
    done = subprocess.run([sys.executable, "-m", "osmo.server.app", "--runtime", "container"],
                          env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 3, done.stderr
    assert "apt-get install podman" in done.stderr and "Traceback" not in done.stderr


def test_pool_list_shows_the_runtime(cosmo: Osmo) -> None:
    nodes = json.loads(cosmo("resource", "list", "--format", "json", check=True).out)
    assert [n["runtime"] for n in nodes] == [f"container (podman {_podman_version()})"]
    table = cosmo("pool", "list", check=True).out
    assert "Runtimes" in table and "container (podman" in table


def _podman_version() -> str:
    return subprocess.run(["podman", "version", "--format", "{{.Client.Version}}"],
                          capture_output=True, text=True, check=True).stdout.strip()


@pytest.mark.parametrize("image", ["--privileged", "alpine:3.18;id", "../../etc/passwd"])
def test_a_hostile_image_name_is_refused_at_submit(cosmo: Osmo, tmp_path: Path,
                                                   image: str) -> None:
    spec = write(tmp_path / "hostile.yaml", f"""
workflow:
  name: hostile
  tasks:
  - name: bad
    image: {json.dumps(image)}
    command: ["true"]
  - name: good
    image: alpine:3.18
    command: [sh, -c, "echo fine"]
""")
    r = cosmo("submit", str(spec), "--wait", timeout=300)
    assert r.code == 2, r  # refused before anything runs, with its position
    assert f"{spec}:6:12: 'image' of task 'bad'" in r.err and "Traceback" not in r.err
    assert cosmo("list", "--format", "json", check=True).json() == []


def test_two_homes_run_the_same_workflow_at_once_apart(
        cosmo: Osmo, podman_env: dict[str, str], engine: ContainerEngine,
        tmp_path: Path) -> None:
    """Two users' servers on one host, the same workflow name (so the same workflow id):
    each has its own containers and its own group network, neither takes the other's name,
    and a group's members reach only their own peers."""
    spec = write(tmp_path / "pair.yaml", """
workflow:
  name: pair
  groups:
  - name: pair
    tasks:
    - name: lead
      lead: true
      image: alpine:3.18
      command: [sh, -c, "hostname -i > {{output}}/ip; sleep 4"]
    - name: peer
      image: alpine:3.18
      command: [sh, -c, "sleep 1; nslookup lead > {{output}}/lead.txt 2>&1; sleep 2"]
""")
    other = container_osmo(tmp_path / "other-home", podman_env)
    try:
        for osmo in (cosmo, other):
            osmo("server", "start", "--cpus", "4", check=True)
        ids = [osmo.submit(spec) for osmo in (cosmo, other)]
        assert ids[0] == ids[1]  # the same id in each home: the names must still differ
        for osmo, wf in zip((cosmo, other), ids, strict=True):
            info = osmo.wait_for(wf, ended, timeout=120)
            assert info["status"] == "COMPLETED", (info, tasks(osmo, wf), task_lines(osmo, wf))
            rows = tasks(osmo, wf)
            lead_ip = (Path(rows["lead"]["output"]) / "ip").read_text().split()
            seen = (Path(rows["peer"]["output"]) / "lead.txt").read_text()
            assert any(ip in seen for ip in lead_ip), (lead_ip, seen)  # its own lead
    finally:
        other.stop_server()
    assert leftovers(engine, owner_labels(other)) == ([], [])


def test_a_container_task_s_cpu_request_is_its_thread_count_unless_spec_or_image_set_it(
        cosmo: Osmo, engine: ContainerEngine, tmp_path: Path) -> None:
    """As for a process, ``OMP_NUM_THREADS`` is the cpu request; the spec's ``environment``
    wins, and so does an image that sets it (its ``ENV``, read from the engine)."""
    tag = f"localhost/osmo-test/omp-{uuid.uuid4().hex[:8]}:1"
    (tmp_path / "Containerfile").write_text("FROM alpine:3.18\nENV OMP_NUM_THREADS=7\n")
    engine.call("build", "--pull=never", "-t", tag, str(tmp_path))
    show = """command: [sh, -c, 'printf %s "${OMP_NUM_THREADS-unset}" > {{output}}/v']"""
    spec = write(tmp_path / "threads.yaml", f"""
workflow:
  name: threads
  resources:
    default: {{cpu: 1}}
    two: {{cpu: 2}}
  tasks:
  - name: two
    resource: two
    image: alpine:3.18
    {show}
  - name: own
    resource: two
    image: alpine:3.18
    environment: {{OMP_NUM_THREADS: "5"}}
    {show}
  - name: imaged
    resource: two
    image: {tag}
    {show}
""")
    try:
        code, wf = submit_wait(cosmo, spec)
        assert code == 0, tasks(cosmo, wf)
        run = Path(cosmo.home) / "runs" / wf
        seen = {name: next(run.glob(f"{name}/*/output/v")).read_text()
                for name in ("two", "own", "imaged")}
        assert seen == {"two": "2", "own": "5", "imaged": "7"}, seen
    finally:
        engine.call("rmi", "-f", tag)
