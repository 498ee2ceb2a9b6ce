"""The examples of the first tutorials and examples/ run for real (docs that say what works today).

The pages' blocks are found by their headings; tests/docs/test_blocks.py checks that each block
these tests run says so (``<!-- run by: ... -->``).
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from tests.conftest import REPO, Osmo
from tests.docs.blocks import first_block, read, section

FIRST = "docs/tutorials/first-workflow.md"
CUSTOM = "docs/tutorials/custom-task-type.md"


def _run_python(code: str, osmo: Osmo) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", code], env=osmo.env, cwd=REPO,
                          capture_output=True, text=True, timeout=180)


def test_examples_sdk_pipeline(shared_osmo: Osmo) -> None:
    proc = subprocess.run([sys.executable, "examples/sdk_pipeline.py"], env=shared_osmo.env,
                          cwd=REPO, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "total = 3410" in proc.stdout  # 385 squares + 3025 cubes
    assert "made from: ['cubes', 'numbers', 'squares', 'total']" in proc.stdout


def test_tutorial_python_example(shared_osmo: Osmo) -> None:
    blocks = re.findall(r"```python\n(.*?)```", section(FIRST, "## From Python"), re.S)
    assert blocks, "the first tutorial has a Python example"
    for code in blocks:
        proc = _run_python(code, shared_osmo)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert "COMPLETED" in proc.stdout


def test_tutorial_cli_examples(shared_osmo: Osmo) -> None:
    usage = first_block(section(FIRST, "## Run a workflow"), "sh")
    commands = [line.split("#")[0].split() for line in usage.splitlines()
                if line.startswith("osmo ")]
    wf_id = ""
    for argv in commands:
        argv = [a.replace("hello-pipeline-1", wf_id or "hello-pipeline-1") for a in argv]
        if argv[1] == "restart":
            continue  # needs a failed workflow; covered by test_lifecycle
        if argv[1:2] == ["artifacts"]:
            argv = [*argv[:-1], str(shared_osmo.home.parent / "readme-out")]
        r = shared_osmo(*argv[1:])
        assert r.code == 0, (argv, r.out, r.err)
        if argv[1] == "submit" and "--dry-run" not in argv:
            wf_id = r.out.splitlines()[0].split(" - ")[1]


def test_tutorial_lineage_walkthrough(shared_osmo: Osmo, tmp_path_factory) -> None:  # type: ignore[no-untyped-def]
    walkthrough = first_block(section(FIRST, "## Where did this file come from?"), "sh")
    workdir = tmp_path_factory.mktemp("walkthrough")
    wf_id, out = "", ""
    for line in walkthrough.splitlines():
        argv = line.split("#")[0].split()
        argv = [a.replace("hello-pipeline-1", wf_id or "hello-pipeline-1") for a in argv]
        argv = [str(workdir / a) if a.startswith("fetched") else a for a in argv]
        proc = subprocess.run([sys.executable, "-m", "osmo", *argv[1:]], env=shared_osmo.env,
                              cwd=REPO, capture_output=True, text=True, timeout=180)
        assert proc.returncode == 0, (argv, proc.stdout, proc.stderr)
        if argv[1] == "submit":
            wf_id = proc.stdout.splitlines()[0].split(" - ")[1]
        out = proc.stdout
    lines = out.splitlines()
    # The producer is this run, or an earlier identical one whose outputs it reused (cache).
    assert lines[0].startswith("report [hello-pipeline-")
    assert any("generate [" in ln for ln in lines) and any("square [" in ln for ln in lines)


def test_tutorial_custom_task_type(shared_osmo: Osmo, tmp_path_factory) -> None:  # type: ignore[no-untyped-def]
    text = read(CUSTOM)
    project = tmp_path_factory.mktemp("custom-types")
    project.chmod(0o755)  # a project folder as people have them (README: a root osmo's tasks
    # run as nobody, and read the type's folder as such)
    (project / "tasks.py").write_text(first_block(text, "py"))
    (project / "workflow.yaml").write_text(first_block(text, "yaml"))
    commands = first_block(text, "sh")
    wf_id, out = "", ""
    for line in commands.splitlines():
        argv = [a.replace("numbers-1", wf_id or "numbers-1") for a in line.split("#")[0].split()]
        proc = subprocess.run([sys.executable, "-m", "osmo", *argv[1:]], env=shared_osmo.env,
                              cwd=project, capture_output=True, text=True, timeout=180)
        assert proc.returncode == 0, (argv, proc.stdout, proc.stderr)
        if argv[1] == "submit":
            wf_id = proc.stdout.splitlines()[0].split(" - ")[1]
        out = proc.stdout
    assert out.startswith(f"numbers [{wf_id}] → sha256:")
    assert out.splitlines()[0].endswith("exit 0: tasks:numbers@1")
    info = shared_osmo.query(wf_id)
    assert (Path(info["tasks"][0]["output"]) / "numbers.txt").read_text() == "1\n2\n3\n"
