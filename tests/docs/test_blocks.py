"""Every command and code block of README.md and docs/ runs, or says why not (tests/docs/blocks.py).

Each page's blocks run in order in a fresh folder of their own, with a fresh ``OSMO_HOME``
whose server the first command starts (and the test stops), so workflow ids are the ones a
reader following the page from the start sees (``hello-pipeline-1``). ``workflows/`` and
``examples/`` of the repository are linked into that folder, as in a clone.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO, Osmo
from tests.docs import blocks as b

# What the pages say their commands print, checked in the combined output of the page.
SAYS = {
    "README.md": ["Workflow ID - hello-pipeline-1", "COMPLETED", "report [hello-pipeline-1]"],
    "docs/how-to/caching.md": [
        "reused 3 tasks instead of running them: generate (from hello-pipeline-1 task generate",
        "reused: the log of hello-pipeline-1 task generate retry 0 follows"],
    "docs/how-to/credentials.md": ["token is ****", "registry://registry.example.com"],
    "docs/how-to/datasets.md": ["count [read-dataset-1]", "dataset frames:1 [upload]",
                                "[read] hello"],
    "docs/how-to/priorities-labels.md": ["HIGH", "team=vision", "best"],
    "docs/how-to/upgrade-backup.md": ["COMPLETED", "from-backup/report.txt"],
}


def test_every_block_runs_or_says_why_not() -> None:
    problems = []
    for page in b.pages():
        problems += [f"{page}:{n}: a fence inside a list is not checked; move it out"
                     for n in b.indented_fences(page)]
        if b.read(page).count("\n```") % 2:
            problems.append(f"{page}: a code block is never closed")
        for block in b.blocks(page):
            problems += [f"{block.where}: {p}" for p in _check(block)]
    assert not problems, "\n".join(problems)


def _check(block: b.Block) -> list[str]:
    if block.marker == b.NOT_RUN:
        named = re.findall(r"tests/[\w/]+\.py", block.detail)
        if not named:
            return ["a block that is not run must name the test that covers it instead"]
        return [f"{t} does not exist" for t in named if not (REPO / t).is_file()]
    if block.marker == b.RUN_BY:
        file, _, test = block.detail.partition("::")
        source = (REPO / file).read_text() if (REPO / file).is_file() else ""
        if f"def {test}(" not in source:
            return [f"no test {block.detail}"]
        if block.page not in source:
            return [f"{file} does not read {block.page}"]
        return []
    if block.marker == b.FILE:
        return [] if re.fullmatch(r"[\w.-]+", block.detail) else ["file: takes a plain file name"]
    if block.lang in b.SHOWN:
        return []
    if block.lang not in b.RUNNABLE:
        return [f"a {block.lang!r} block needs a marker (run by, not run or file)"]
    if block.lang == "yaml" and not re.search(r"^workflow:", block.code, re.M):
        return ["a yaml block that is no workflow needs a marker"]
    return []


RUN = [page for page in b.pages() if any(blk.marker is None for blk in b.to_run(page))]


def test_the_runnable_pages_are_the_expected_ones() -> None:
    assert set(SAYS) <= set(RUN), set(SAYS) - set(RUN)


@pytest.mark.parametrize("page", RUN)
def test_a_page_runs(page: str, tmp_path: Path) -> None:
    for name in ("workflows", "examples"):
        (tmp_path / name).symlink_to(REPO / name)
    osmo = Osmo(tmp_path / "home")
    out = []
    try:
        for block in b.to_run(page):
            out.append(_run(block, tmp_path, osmo))
    finally:  # every server a page started, in its home or another (by PID)
        for found in tmp_path.rglob("server.json"):
            Osmo(found.parent).stop_server()
    text = "\n".join(out)
    missing = [s for s in SAYS.get(page, []) if s not in text]
    assert not missing, f"{page} says its commands print {missing}; they printed:\n{text}"


def _run(block: b.Block, folder: Path, osmo: Osmo) -> str:
    if block.marker == b.FILE:
        (folder / block.detail).write_text(block.code)
        return ""
    if block.lang == "sh":
        prelude = f'osmo() {{ "{sys.executable}" -m osmo "$@"; }}\n'
        argv = ["bash", "-euo", "pipefail", "-c", prelude + block.code]
    elif block.lang == "python":
        argv = [sys.executable, "-c", block.code]
    else:  # a yaml workflow
        spec = folder / f"block-{block.line}.yaml"
        spec.write_text(block.code)
        argv = [sys.executable, "-m", "osmo", "validate", str(spec)]
    env = dict(osmo.env, PYTHONPATH=str(REPO))
    proc = subprocess.run(argv, cwd=folder, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, (f"{block.where} exited {proc.returncode}\n{block.code}\n"
                                  f"stdout:\n{proc.stdout}\nstderr:\n{proc.stderr}")
    return proc.stdout + proc.stderr
