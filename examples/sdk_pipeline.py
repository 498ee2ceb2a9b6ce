"""Build a small pipeline in Python, run it, then ask where its result came from.

Run it (a local server starts by itself):  python examples/sdk_pipeline.py
"""

from __future__ import annotations

import osmo


def build() -> osmo.Workflow:
    """numbers → squares and cubes in parallel → total."""
    wf = osmo.Workflow("sdk-pipeline")
    wf.task("numbers", ["sh", "-c", "seq 1 10 > {{output}}/n.txt"])
    wf.task("squares", ["sh", "-c",
                        "for n in $(cat {{input:numbers}}/n.txt); do echo $((n*n)); done"
                        " > {{output}}/v.txt"], inputs=["numbers"])
    wf.task("cubes", ["sh", "-c",
                      "for n in $(cat {{input:numbers}}/n.txt); do echo $((n*n*n)); done"
                      " > {{output}}/v.txt"], inputs=["numbers"])
    wf.task("total", ["sh", "-c",
                      "t=0; for n in $(cat {{input:squares}}/v.txt {{input:cubes}}/v.txt); "
                      "do t=$((t+n)); done; echo $t | tee {{output}}/total.txt"],
            inputs=["squares", "cubes"])
    return wf


def main() -> int:
    with osmo.Client() as client:
        wf_id = client.submit(build())
        result = client.wait(wf_id)
        for task in result.tasks:
            print(f"{task.name:8s} {task.status.name:10s} exit {task.exit_code}"
                  f"{'  (cached)' if task.reused else ''}")
        if not result.ok:
            return 1
        total = [r.text for r in client.logs(wf_id, task="total") if r.stream == "stdout"]
        print("total =", total[-1])
        upstream = client.lineage(f"{wf_id}:total")
        print("made from:", sorted(n["task"] for n in upstream["nodes"].values()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
