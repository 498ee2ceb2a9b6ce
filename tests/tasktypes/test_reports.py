"""``osmo eval report`` shows whatever rows a task type declares, knowing nothing of its files.

The task type here comes from a distribution of its own on ``sys.path`` (a ``*.dist-info``
with an ``osmo.task_types`` entry point), as a third party's would: its report reads
``counts.json`` files, a format the core has never heard of.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from osmo.cli.main import main
from osmo.tasktypes.reports import Report, installed_reports
from tests.conftest import Osmo, write
from tests.tasktypes.conftest import write_dist

DEMO = '''
from osmo.tasktypes.api import task_type
from osmo.tasktypes.reports import Table


class Counts:
    file = "counts.json"

    def problem(self, data):
        return None if isinstance(data, dict) and "counts" in data else "no counts"

    def table(self, sources):
        rows = tuple({"workflow": s.workflow, "task": s.task, "name": k, "n": v}
                     for s in sources for k, v in sorted(s.data["counts"].items()))
        return Table(("Name", "N", "From"), tuple((r["name"], str(r["n"]), r["workflow"])
                                                  for r in rows),
                     rows, ("counted by demo.count",))


@task_type("demo.count", version="1")
def COUNT(ctx):
    """Counts things."""


COUNT.report = Counts()
'''


@pytest.fixture
def demo(on_path: Path) -> Path:
    write_dist(on_path, "osmo_demo_count", {"demo.count": "osmo_demo_count:COUNT"})
    (on_path / "osmo_demo_count.py").write_text(DEMO)
    return on_path


def test_an_installed_type_that_declares_a_report_is_found(demo: Path) -> None:
    reports = installed_reports()
    assert isinstance(reports["demo.count"], Report) and reports["demo.count"].file == \
        "counts.json"
    assert reports["sim.eval"].file == "metrics.json"  # the built-in one, found the same way


def test_its_rows_are_shown_as_it_declares_them(demo: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path / "counts.json", json.dumps({"counts": {
        "apples": 3, "pears\x1b[2J": 12}}))
    assert main(["eval", "report", str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out == ["Name          N   From", "apples        3   -",
                   "pears\\033[2J  12  -", "", "counted by demo.count"]
    assert main(["eval", "report", str(path), "--format", "json"]) == 0
    assert json.loads(capsys.readouterr().out) == [
        {"workflow": "-", "task": str(path), "name": "apples", "n": 3},
        {"workflow": "-", "task": str(path), "name": "pears\x1b[2J", "n": 12}]


def test_a_file_no_report_reads_is_refused_naming_every_report(
        demo: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path / "x.json", "{}")
    assert main(["eval", "report", str(path)]) == 2
    err = capsys.readouterr().err
    assert "not a demo.count counts.json or sim.eval metrics.json (no counts)" in err


def test_the_rows_of_a_workflows_outputs(demo: Path, tmp_path: Path) -> None:
    """Through a real server: the report's files are found among a workflow's outputs."""
    osmo = Osmo(tmp_path / "home")
    osmo.env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(demo),
                                                           os.environ.get("PYTHONPATH")]))
    spec = write(tmp_path / "counted.yaml", """
workflow:
  name: counted
  tasks:
  - name: count
    command: [python3, -c, "import json, os; json.dump(dict(counts=dict(apples=3)),
      open(os.environ['OSMO_OUTPUT'] + '/counts.json', 'w'))"]
""")
    try:
        wf = osmo.submit(spec, "--wait")
        rows = osmo("eval", "report", wf, "--format", "json", check=True).json()
        assert rows == [{"workflow": wf, "task": "count", "name": "apples", "n": 3}]
        text = osmo("eval", "report", wf, check=True).out.splitlines()
        assert text[1].split() == ["apples", "3", wf] and text[-1] == "counted by demo.count"
    finally:
        osmo.stop_server()
