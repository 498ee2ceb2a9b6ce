"""The vision pipeline end to end: wall time and what the trained policy reaches.

Submits ``workflows/reach-vision.yaml`` through the real CLI to a fresh local server (its own
OSMO_HOME, so nothing is cached), waits for it, and reads ``osmo eval report``: the trained
ACT policy, the scripted expert and random on the same unseen seeds. Rows:

- wall time, submit → COMPLETED (target ≤ 600 s on 2 cores);
- success rate of the trained policy, the expert and random (the env's own signal);
- trained success as a fraction of the expert's (target ≥ 0.8);
- the trained policy's normalised return, (return - random) / (expert - random) (target 0.8).

One run is one sample (the pipeline is seeded end to end; the spread comes from the machine).
Needs every extra (sim, learn) and offscreen OpenGL.

Usage: python bench/bench_pipeline.py [--runs 1] [--set K=V ...] [--json out.json]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

from benchlib import quick, row, write_rows  # noqa: E402

ENV = "osmo/ReachVision-v1"
TINY = ["shards=2", "episodes=2", "steps=20", "eval_episodes=2"]


def osmo_cli(home: Path, *args: str, timeout: float = 3600) -> str:
    """Run ``osmo ARGS`` with ``OSMO_HOME=home``; its stdout (RuntimeError when it fails)."""
    env = dict(os.environ, OSMO_HOME=str(home))
    env.pop("OSMO_SERVER", None)
    proc = subprocess.run([sys.executable, "-m", "osmo", *args], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"osmo {' '.join(args)} exited {proc.returncode}:\n"
                           f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc.stdout


def submit_wait(home: Path, spec: Path, settings: list[str]) -> tuple[float, str]:
    """``osmo submit SPEC --wait --set ...`` to the server of ``home``: seconds and workflow id.

    The seconds run from starting the CLI to its exit (the workflow COMPLETED).
    """
    sets = [a for s in settings for a in ("--set", s)]
    start = time.perf_counter()
    out = osmo_cli(home, "submit", str(spec), "--wait", *sets)
    elapsed = time.perf_counter() - start
    wf = next(ln for ln in out.splitlines() if ln.startswith("Workflow ID - ")).split(
        " - ", 1)[1].strip()
    return elapsed, wf


def one_run(settings: list[str]) -> tuple[float, dict[str, dict[str, Any]]]:
    """Seconds from submit to COMPLETED, and the eval rows by policy."""
    with tempfile.TemporaryDirectory() as tmp:
        home = Path(tmp)
        osmo_cli(home, "server", "start")  # not part of the pipeline's time
        elapsed, wf = submit_wait(home, ROOT / "workflows/reach-vision.yaml", settings)
        rows = json.loads(osmo_cli(home, "eval", "report", wf, "--format", "json"))
        osmo_cli(home, "server", "stop")
    return elapsed, {r["policy"]: r for r in rows if r["env"] == ENV}


def main() -> None:
    """Run the pipeline ``--runs`` times and record the rows."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--set", dest="settings", action="append", default=[],
                        metavar="K=V", help="a workflow default-value to override")
    parser.add_argument("--json")
    args = parser.parse_args()
    missing = [m for m in ("gymnasium", "mujoco", "lerobot", "foxglove")
               if importlib.util.find_spec(m) is None]
    if missing:
        print(f"skipped: needs {', '.join(missing)} (pip install \"osmo[all]\")")
        write_rows(args.json, [])
        return
    settings = TINY + args.settings if quick() else args.settings
    times: list[float] = []
    found: list[dict[str, dict[str, Any]]] = []
    for _ in range(max(1, 1 if quick() else args.runs)):
        elapsed, rows = one_run(settings)
        times.append(elapsed)
        found.append(rows)
    note = "settings: " + (" ".join(settings) or "the workflow's defaults")
    rate = {p: [100 * (f[p]["success_rate"] or 0) for f in found]
            for p in ("train", "expert", "random")}
    rows = [row("pipeline: reach-vision wall time, submit → COMPLETED", "s", times,
                higher_is_better=False, target=600.0, notes=note)]
    rows += [row(f"pipeline: reach-vision {p} success rate", "%", v, higher_is_better=True)
             for p, v in rate.items()]
    rows.append(row("pipeline: reach-vision trained success / expert success", "x",
                    [t / e if e else 0.0 for t, e in zip(rate["train"], rate["expert"],
                                                         strict=True)],
                    higher_is_better=True, target=0.8))
    rows.append(row("pipeline: reach-vision trained normalised return", "x",
                    [f["train"]["normalized_score"] or 0.0 for f in found],
                    higher_is_better=True, target=0.8))
    write_rows(args.json, rows)


if __name__ == "__main__":
    main()
