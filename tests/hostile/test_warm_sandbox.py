"""A custom type's import code under the default sandbox (issue 30), through the real CLI.

The attack a sandboxed warm start must withstand: a type's module runs code when it is
imported (once, in a warm runner, if sandboxed warm starts exist) and leaves a hook behind
(a patched ``os.fork``, called for every later fork). From there it looks for osmo's home
and for the files of another attempt. Started cold in the sandbox, its import runs inside
the attempt's own view: it sees its own attempt's folder and nothing else of the home.

A sandboxed typed attempt still starts cold (``docs/how-to/warm-runners.md``): a runner is
the parent of its attempts, with their uid in the node's user namespace, so its code reads
an attempt's folders through ``/proc/PID/root`` once that attempt runs any program
(``bench/warm_sandbox_probe.py``). Whoever builds sandboxed warm starts keeps this test
green with them on.
"""

from __future__ import annotations

import json
from pathlib import Path

from tests.conftest import Osmo, write

SPY = r'''
import json, os
from pathlib import Path
from osmo import Param, task_type

HOME = Path(__HOME__)


def _look():
    """Every file of osmo's home this process can list, and whether it holds a secret."""
    found = {}
    for folder, _, files in os.walk(HOME):
        for name in files:
            path = os.path.join(folder, name)
            try:
                with open(path, "rb") as file:
                    found[path] = b"SECRET-" in file.read(1 << 16)
            except OSError:
                found[path] = False
    return found


AT_IMPORT = _look()
LATER = {}
_fork = os.fork


def _spying_fork():
    LATER.update(_look())
    return _fork()


os.fork = _spying_fork


@task_type(version="1", params={"mode": Param(str, default="spy")})
def spy(ctx):
    """plant: leave a secret in its folder and its output; then report what it saw."""
    work = Path(os.getcwd())
    if ctx.params["mode"] == "plant":
        (work / "planted.txt").write_text("SECRET-" + "planted")
        (ctx.output / "planted.txt").write_text("SECRET-" + "planted")
    seen = {**AT_IMPORT, **LATER, **_look()}
    (ctx.output / "seen.json").write_text(json.dumps({"mine": str(work.parent), "seen": seen,
                                                      "at_import": len(AT_IMPORT)}))
'''

PLANT = """
workflow:
  name: plant
  tasks:
  - name: plant
    type: spytypes:spy
    params: {mode: plant}
"""

LOOK = """
workflow:
  name: look
  tasks:
  - name: look
    type: spytypes:spy
"""


def _seen(osmo: Osmo, wf_id: str, task: str) -> dict:
    info = {t["name"]: t for t in osmo.query(wf_id)["tasks"]}
    return json.loads((Path(info[task]["output"]) / "seen.json").read_text())


def test_import_code_sees_only_its_own_attempt(osmo: Osmo, tmp_path: Path) -> None:
    osmo("server", "start", check=True)  # the default sandbox (bubblewrap), warm starts on
    project = tmp_path / "project"
    write(project / "spytypes.py", SPY.replace("__HOME__", repr(str(osmo.home))))
    planted = osmo.submit(write(project / "plant.yaml", PLANT), "--wait")
    looked = osmo.submit(write(project / "look.yaml", LOOK), "--wait")
    for wf, task in ((planted, "plant"), (looked, "look")):
        report = _seen(osmo, wf, task)
        mine = report["mine"].rstrip("/") + "/"
        outside = sorted(p for p in report["seen"] if not p.startswith(mine))
        assert not outside, (task, outside[:20])  # nothing of the home but its own attempt
    report = _seen(osmo, looked, "look")
    assert not any(report["seen"].values()), report  # the planted secret never reached it
    assert Path(_seen(osmo, planted, "plant")["mine"], "work", "planted.txt").exists()
