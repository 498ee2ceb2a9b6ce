"""bench/run --quick: every bench script runs and the report has the expected rows.

Behaviour only: the sizes are tiny and no number is compared with anything, so a slow or
busy machine never fails this. The peer comparison (which installs Prefect and Ray) is not
run here.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.slurm.cluster import missing_programs

REPO = Path(__file__).resolve().parents[2]
RUN = REPO / "bench" / "run"

EXPECTED = [
    "osmo fan-out/join 20 `true` tasks",
    "osmo chain 20 `true` tasks",
    "osmo fan-out/join 60 `true` tasks",
    "ingest: 8 MiB file, new blob, same filesystem (link)",
    "lineage: overhead per task (total)",
    "limit: spawn `true`, 2 parallel, no orchestrator",
    "limit: zenoh get round trip p50",
    "limit: zenoh get round trip p99",
    "limit: zenoh put throughput",
    "limit: sha256 of a file (page cache, 1 MiB reads)",
    "startup: submit → first task running (SDK)",
    "startup: submit → first task running (CLI `osmo submit`)",
    "startup: auto-started server ready (CLI, no server running)",
    "remote: no-op task round trip p50 (placed → completed)",
    "remote: what the remote hop adds to a task's round trip, p50",
    "remote: what the remote hop adds to a task's round trip, p99",
    "remote: output transfer (8 MiB, worker → server)",
    "remote: fan-out/join 20 `true` tasks over 2 workers",
    "remote: fan-out/join 20 `true` tasks on the local pool",
    "remote: fan-out over 2 workers ÷ the same on the local pool",
    "limit: raw loopback TCP, 8 MiB, 1 stream",
    "port-forward (remote worker), 8 MiB, 1 stream",
    "port-forward (remote worker), 8 MiB, 20 streams",
    "port-forward (remote worker), 1-byte round trip p50",
    "submit: 2,000-task fan-out",
    "server CPU for the submit: 2,000-task fan-out",
    "query: running 2,000-task workflow",
    "list (20 rows): 50 finished workflows",
    "log writer, capped at 64 MiB: per line",
    "log writer, uncapped: per line",
    "osmo logs of a huge log",
    "osmo logs: server peak RSS over idle",
    "osmo logs: client peak RSS",
]
DATAGEN = [
    "datagen: 2 workers / 1 worker",
    "datagen: recording overhead (recorded vs bare time per step)",
    "datagen: recording overhead with 64x64 frames",
]
SLURM = [
    "limit: slurm `sbatch --wait` of `true`, 1 job",
    "slurm: `sbatch --wait` of `true`, N in parallel, per job",
    "slurm: submit → RUNNING, 1 job (the scheduler's cycle)",
    "slurm: N jobs submitted back to back → all COMPLETED, per job",
]
WARM_SANDBOX = [  # bench_warm_sandbox.py: root and osmo[sim]
    "warm sandbox: one sim.rollout start, warm",
    "warm sandbox: one sim.rollout start, cold",
    "warm sandbox: cold ÷ warm start",
]
PIPELINE = [
    "pipeline: reach-vision wall time, submit → COMPLETED",
    "pipeline: reach-vision trained success / expert success",
    # bench_sim.py, osmo's side (the quick run skips the pipeline; Ray only with --peers)
    "sim: rollout sweep (4 tasks), osmo makespan",
    "sim: rollout sweep (4 tasks), osmo overhead per task",
    "sim: evaluation sweep (2 tasks), osmo makespan",
    "sim: evaluation sweep (2 tasks), osmo overhead per task",
]


def run(*args: str, timeout: float = 480) -> subprocess.CompletedProcess[str]:
    """bench/run with this interpreter's environment (no pip)."""
    return subprocess.run([sys.executable, str(REPO / "bench" / "suite.py"), *args],
                          capture_output=True, text=True, timeout=timeout, cwd=REPO)


def test_bench_run_is_executable_and_takes_no_setup() -> None:
    text = RUN.read_text()
    assert RUN.stat().st_mode & 0o111
    assert "--no-setup" in text and "bench/suite.py" in text


@pytest.mark.timeout(900)  # ~3 min alone; at load 8 on 2 cores it took over 8
def test_quick_run_writes_every_expected_row(tmp_path: Path) -> None:
    proc = run("--quick", "--out", str(tmp_path), timeout=840)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    report = json.loads((tmp_path / "latest.json").read_text())
    assert {"cpu", "cores", "python", "kernel", "date"} <= set(report["machine"])
    sim = importlib.util.find_spec("gymnasium") is not None  # the datagen bench needs osmo[sim]
    learn = sim and importlib.util.find_spec("lerobot") is not None  # the pipeline: osmo[all]
    slurm = not missing_programs() and os.geteuid() == 0  # the Slurm bench: root, slurm-wlm
    for script in report["scripts"]:
        wanted = "skipped" if (script["script"] == "bench_datagen" and not sim) or (
            script["script"] in ("bench_pipeline", "bench_sim") and not learn) or (
            script["script"] == "bench_slurm" and not slurm) or (
            script["script"] == "bench_warm_sandbox" and not (sim and os.geteuid() == 0)) \
            else "ok"
        assert script["status"] == wanted, script
    rows = {r["name"]: r for r in report["rows"]}
    expected = (EXPECTED + (DATAGEN if sim else []) + (PIPELINE if learn else [])
                + (SLURM if slurm else []) + (WARM_SANDBOX if sim and os.geteuid() == 0 else []))
    for name in expected:
        assert name in rows, f"missing row {name!r}; have {sorted(rows)}"
        r = rows[name]
        for key in ("median", "min", "max"):
            assert isinstance(r[key], (int, float)) and math.isfinite(r[key]), (name, r)
        assert r["min"] <= r["median"] <= r["max"] and r["runs"] >= 1
    # limits resolved across scripts, and the targets checked (pass or fail, never an error)
    fan = rows["osmo fan-out/join 20 `true` tasks"]
    assert fan["limit"] == rows["limit: spawn `true`, 2 parallel, no orchestrator"]["median"]
    assert 0 < fan["fraction_of_limit"]
    assert isinstance(rows["startup: submit → first task running (SDK)"]["pass"], bool)
    assert any(n.startswith("derived: ") and "pass" in r for n, r in rows.items())
    md = (tmp_path / "latest.md").read_text()
    assert "## Targets" in md and report["machine"]["cpu"] in md
    for name in expected:
        assert f"| {name} |" in md


def test_a_failing_script_is_reported_and_the_others_still_run(tmp_path: Path) -> None:
    scripts = tmp_path / "scripts"
    scripts.mkdir()
    (scripts / "bench_good.py").write_text(
        "import json, sys\n"
        "rows = [{'name': 'good', 'unit': 'x/s', 'median': 2.0, 'min': 1.0, 'max': 3.0,\n"
        "         'runs': 3, 'higher_is_better': True, 'limit': 4.0}]\n"
        "open(sys.argv[sys.argv.index('--json') + 1], 'w').write(json.dumps(rows))\n")
    (scripts / "bench_broken.py").write_text("raise SystemExit('it broke')\n")
    (scripts / "bench_badrows.py").write_text(
        "import sys\nopen(sys.argv[sys.argv.index('--json') + 1], 'w').write('[{\"name\": 1}]')\n")
    proc = run("--scripts", str(scripts), "--out", str(tmp_path / "out"), timeout=60)
    assert proc.returncode == 1
    report = json.loads((tmp_path / "out" / "latest.json").read_text())
    status = {s["script"]: s["status"] for s in report["scripts"]}
    assert status == {"bench_good": "ok", "bench_broken": "failed", "bench_badrows": "failed"}
    rows = {r["name"]: r for r in report["rows"]}
    assert rows["good"]["fraction_of_limit"] == 0.5
    assert "it broke" in rows["bench_broken: FAILED"]["notes"]
    assert "| bench_broken: FAILED |" in (tmp_path / "out" / "latest.md").read_text()
