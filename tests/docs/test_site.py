"""The documentation site builds with warnings as errors, and its generated reference is whole.

``mkdocs build --strict`` fails on a broken link, a missing anchor, a page left out of the nav or
a docstring mkdocstrings cannot read; ``./dev test`` installs the ``docs`` extra, so in a full
run this cannot skip (OSMO_NO_SKIPS). The reference pages that are written by hand are checked
against the code they describe: every spec key, status and exit code appears.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from osmo.spec import parse, parse_io, parse_task
from osmo.status import ExitCode, TaskStatus, WorkflowStatus
from tests.conftest import REPO
from tests.docs.blocks import pages, read

sys.path.insert(0, str(REPO / "docs" / "hooks"))
import osmo_docs  # noqa: E402  (the site's hook, imported from its folder)


def test_the_site_builds_strict(tmp_path: Path) -> None:
    if importlib.util.find_spec("mkdocs") is None:  # a failure in a full run (OSMO_NO_SKIPS)
        pytest.skip('the docs extra is not installed: pip install -e ".[docs]" (./dev test does)')
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d",
                           str(tmp_path / "site")], cwd=REPO, capture_output=True, text=True,
                          timeout=300, env=dict(os.environ, NO_MKDOCS_2_WARNING="1"))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    site = tmp_path / "site"
    cli = (site / "reference" / "cli" / "index.html").read_text()
    assert "osmo dataset upload" in cli and "--sandbox-share" in cli
    assert "doc-heading" in (site / "reference" / "sdk" / "index.html").read_text()
    assert "image.repository" in (site / "reference" / "helm-values" / "index.html").read_text()
    assert (site / "images" / "submit-wait.svg").is_file()
    assert (site / "images" / "rerun-eval.png").is_file()  # docs/images/make_rerun_view.py
    assert "Not run by the docs tests" in (site / "tutorials" / "robotics" / "index.html").read_text()


def test_the_pictures_come_from_a_real_run(tmp_path: Path) -> None:
    script = REPO / "docs" / "images" / "make_screenshots.py"
    proc = subprocess.run([sys.executable, str(script), "--out", str(tmp_path)], cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    wait, reuse = (tmp_path / "submit-wait.svg").read_text(), (
        tmp_path / "submit-reuse.svg").read_text()
    text = " ".join(re.findall(r">([^<]*)</text>", wait)).replace("&#160;", " ")
    assert "Workflow ID - hello-pipeline-1" in text and "4/4 tasks done" in text
    assert text.count("hello-pipeline-1  COMPLETED") == 1  # the last frame only
    assert "reused 3 tasks" in " ".join(re.findall(r">([^<]*)</text>", reuse)).replace(
        "&#160;", " ")
    assert "COMPLETED" in (tmp_path / "query.svg").read_text()
    for name in ("submit-wait.svg", "query.svg", "submit-reuse.svg"):
        assert (REPO / "docs" / "images" / name).is_file(), f"{name} is not committed"


def _verbs(parser: argparse.ArgumentParser, path: str) -> list[str]:
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and path != "osmo workflow":
            for name, sub in action.choices.items():
                if name in {c.dest for c in action._choices_actions}:
                    out += [f"{path} {name}", *_verbs(sub, f"{path} {name}")]
    return out


def test_the_cli_reference_has_every_verb_and_option() -> None:
    from osmo.cli.main import build_parser

    text = osmo_docs.cli_markdown()
    parser = build_parser()
    verbs = _verbs(parser, "osmo")
    assert "osmo dataset upload" in verbs and "osmo workflow exec" not in verbs
    missing = [v for v in verbs if f"`{v}`" not in text]
    assert not missing, missing
    assert "`--priority PRIORITY`" in text and "One of: `HIGH`, `NORMAL`, `LOW`" in text


def test_the_helm_values_reference_has_every_documented_key() -> None:
    values = (REPO / "helm" / "osmo" / "values.yaml").read_text()
    rows = osmo_docs.helm_values()
    assert len(rows) == values.count("# --")
    keys = {k for k, _, _ in rows}
    assert {"image.repository", "server.persistence.size", "pools", "worker.drainTimeout"} <= keys
    data = yaml.safe_load(values)
    assert dict((k, v) for k, v, _ in rows)["server.persistence.size"] == (
        data["server"]["persistence"]["size"])


def test_the_spec_reference_names_every_key() -> None:
    text = read("docs/reference/spec.md")
    keys = {*parse.DOC_KEYS, *parse.WORKFLOW_KEYS, *parse.GROUP_KEYS, *parse.RESOURCE_KEYS,
            *parse.TOPOLOGY_KEYS, *parse.TIMEOUT_KEYS, *parse_task.TASK_KEYS,
            *parse_io._FILE_KEYS, *parse_io._CHECKPOINT_KEYS}
    missing = sorted(k for k in keys if not re.search(rf"\b{re.escape(k)}\b", text))
    assert not missing, f"docs/reference/spec.md does not mention {missing}"


def test_the_exit_code_reference_names_every_status_and_code() -> None:
    text = read("docs/reference/exit-codes.md")
    names = [f"`{s.value}`" for s in [*TaskStatus, *WorkflowStatus]]
    codes = [str(v) for k, v in vars(ExitCode).items() if k.isupper() and isinstance(v, int)]
    missing = [n for n in [*names, *codes] if n not in text]
    assert not missing, missing


def _slug(heading: str) -> str:
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def test_the_readme_is_a_front_door_whose_links_lead_somewhere() -> None:
    readme = read("README.md")
    assert len(readme.splitlines()) <= 200
    for command in ("./dev demo", "./dev test", "./dev docs"):
        assert command in readme
    links = re.findall(r"\]\(([^)#\s]+)(?:#([^)\s]+))?\)", readme)
    assert len(links) > 20
    for target, anchor in links:
        path = REPO / target
        assert path.is_file(), f"README links to {target}, which does not exist"
        if anchor:
            slugs = {_slug(h) for h in re.findall(r"^#+ (.*)$", path.read_text(), re.M)}
            assert anchor in slugs, f"README links to {target}#{anchor}: no such heading"


def test_the_sdk_reference_documents_every_public_name() -> None:
    import osmo

    text = read("docs/reference/sdk.md")
    errors = re.search(r"::: osmo\.errors\n.*?members: \[(.*?)\]", text, re.S)
    assert errors is not None
    listed = {f"::: osmo.{n}" for n in osmo.__all__} - {
        f"::: osmo.{n.strip()}" for n in errors.group(1).split(",")}
    missing = sorted(n for n in listed if f"{n}\n" not in text)
    assert not missing, f"docs/reference/sdk.md does not document {missing}"


def test_lists_render_as_written() -> None:
    """Python-Markdown nests a list only under four spaces, and starts one only after a blank
    line: a list written otherwise renders flat, or as running text."""
    problems = []
    for page in pages():
        fence, prev = False, ""
        for n, line in enumerate(read(page).splitlines(), 1):
            if line.startswith("```"):
                fence = not fence
            elif not fence and re.match(r"^ {1,3}[-*] ", line):
                problems.append(f"{page}:{n}: a nested item needs four spaces")
            elif not fence and line.startswith("- ") and prev.strip() and not re.match(
                    r"^(\s|- )", prev):
                problems.append(f"{page}:{n}: a list needs a blank line before it")
            prev = line
    assert not problems, "\n".join(problems)
