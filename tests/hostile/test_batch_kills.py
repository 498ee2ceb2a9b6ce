"""Issue 16: the engine commits many attempts' completions in one transaction; a ``kill -9`` of
the server in the middle of such a batch loses none and commits none twice.

A real server (``tests/hostile/faulty_server.py``, fault ``batch``) runs 8 tasks at once that
all finish together, applies their exits in one batch and SIGKILLs itself before, during or
after that batch's commit. The next server is started by the real CLI. Checked from the
state store and the tasks' own start log: the workflow COMPLETED, each task has exactly one
COMPLETED transition and one lineage record for its output, nothing is quarantined, and a
completion that was committed is never run again.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest

from osmo.store.sqlite import Store
from tests.conftest import Osmo, write
from tests.hostile.test_engine_faults import Faulty, faulty  # noqa: F401 - the fixture

WIDTH = 8


def spec(go: Path, starts: Path) -> str:
    """``WIDTH`` tasks that wait for ``go`` then finish together, and a join of them all."""
    body = (f"echo $0 >> {starts}; while [ ! -e {go} ]; do sleep 0.01; done; "
            "echo $0 > {{output}}/out.txt")
    names = [f"w{i}" for i in range(WIDTH)]
    tasks = "".join(f"""
  - name: {name}
    command: [sh, -c, "{body}", {name}]
""" for name in names)
    return f"""
workflow:
  name: together
  tasks:{tasks}
  - name: join
    inputs: [{", ".join(f"{{task: {n}}}" for n in names)}]
    command: [sh, -c, "echo join >> {starts}; cat {{{{input:w0}}}}/out.txt > {{{{output}}}}/all"]
"""


@pytest.mark.parametrize("phase", ["before", "during", "after"])
def test_a_kill_in_the_middle_of_a_batch_of_completions_loses_and_repeats_nothing(
        osmo: Osmo, faulty: list[Faulty], tmp_path: Path, phase: str) -> None:  # noqa: F811
    go, starts, marker = tmp_path / "go", tmp_path / "starts", tmp_path / "killed"
    server = Faulty(osmo, f"batch:{phase}:3:{marker}", "--cpus", str(WIDTH))
    faulty.append(server)
    wf = osmo.submit(write(tmp_path / "wf.yaml", spec(go, starts)))
    osmo.wait_for(wf, lambda i: sum(t["status"] == "RUNNING" for t in i["tasks"]) == WIDTH,
                  timeout=60)
    go.touch()  # all finish at once: their exits are applied in one batch
    server.killed_itself(marker)

    info = osmo.wait_for(wf, lambda i: i["status"] not in ("PENDING", "RUNNING", "WAITING"),
                         timeout=120)  # the CLI starts the next server (no fault)
    assert info["status"] == "COMPLETED", info
    assert not [t for t in info["tasks"] if t["message"].startswith("quarantined")]
    store = Store(osmo.home / "state.db")
    try:
        completed = Counter(e["task"] for e in store.transitions(wf)
                            if e["task"] is not None and e["status"] == "COMPLETED")
        outputs = store.outputs(wf)
        lineage = {o["task"]: len(store.lineage_of_manifest(o["manifest"])) for o in outputs}
    finally:
        store.close()
    names = [f"w{i}" for i in range(WIDTH)] + ["join"]
    assert completed == Counter(names), completed
    assert lineage == dict.fromkeys(names, 1), lineage
    ran = Counter(starts.read_text().split())
    assert ran["join"] == 1
    if phase == "after":  # the batch was committed: no completed task runs again
        assert ran == Counter(names), ran
    else:  # not committed: the batch's tasks run again once, as new retries (first strike)
        again = {name for name, n in ran.items() if n > 1}
        assert again and all(ran[n] <= 2 for n in names), ran
        assert {t["name"] for t in info["tasks"] if t["retry"] == 1} == again
    assert not (osmo.home / "applying.json").read_bytes()
