"""The workflow of ``workflow.yaml`` built in Python, with the type objects themselves.

Run from anywhere: ``python examples/custom_task/build.py``.
"""

from __future__ import annotations

from pathlib import Path

import osmo
import tasks  # this folder is on sys.path when the script runs

wf = osmo.Workflow("custom-task-sdk")
wf.task("numbers", type=tasks.numbers, params={"count": 10})
wf.task("cubes", type=tasks.power, params={"exponent": 3}, inputs=["numbers"])

with osmo.Client() as client:
    result = client.wait(client.submit(wf))
    print(result.status.name)
    powers = Path(result.task("cubes").output or "") / "powers.txt"
    print("sum of cubes =", sum(int(n) for n in powers.read_text().split()))
