"""The benchmark harness behind ``bench/run``: run every bench script, write one report.

Runs each ``bench_*.py`` in the scripts folder (and, with ``--peers``, ``peers/compare.py``)
as its own process with ``--json FILE``, collects the rows (the protocol is in
``benchlib.py``), and writes ``latest.json`` and ``latest.md`` into the results folder, with
the machine (cpu model, cores, python, kernel, date). A script that exits non-zero, times
out or writes no valid rows shows up as a FAILED row; the others still run. A script that
writes an empty list (its extra is not installed) is marked skipped. The exit code is 1 if
any script failed, else 0: slowness never fails the run.

After collecting, the harness:

- resolves ``limit_of`` (a row naming another row as its limit) and a few known pairs
  (``DEFAULT_LIMITS``: e.g. any remote dispatch round trip → zenoh's get round trip), then
  shows each figure as a fraction of its limit (value/limit when higher is better,
  limit/value when lower is better: 100% means osmo adds nothing);
- derives the engine's overhead per task against the spawn limit;
- checks every row that carries a ``target`` and lists them as pass/fail.

Usage: python bench/suite.py [--quick] [--peers] [--only REGEX] [--out DIR]
       [--scripts DIR] [--timeout S]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from benchlib import Row, machine_info  # noqa: E402

REQUIRED = {"name": str, "unit": str, "median": (int, float), "min": (int, float),
            "max": (int, float), "runs": int, "higher_is_better": bool}
SPAWN = "limit: spawn `true`, 2 parallel, no orchestrator"
# Rows that name no limit get one by pattern, so later scripts (remote, datagen) need not know
# the limit rows' names.
DEFAULT_LIMITS = [
    (re.compile(r"remote.*(round trip|dispatch|latency)", re.I), "limit: zenoh get round trip p50"),
    (re.compile(r"^osmo .*`true` tasks$"), SPAWN),
]


def run_script(script: Path, out_dir: Path, env: dict[str, str], timeout: float
               ) -> tuple[dict[str, Any], list[Row]]:
    """Run one script; return its record (status, seconds, log) and its rows."""
    name = script.stem if script.parent.name != "peers" else "peers"
    log_path = out_dir / "logs" / f"{name}.log"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    fd, json_path = tempfile.mkstemp(prefix=f"{name}-", suffix=".json")
    os.close(fd)
    print(f"== {name}", flush=True)
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, str(script), "--json", json_path], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)

    def kill() -> None:  # the script's own process group, started above
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    timer = threading.Timer(timeout, kill)
    timer.start()
    tail: list[str] = []
    with open(log_path, "w") as log:
        assert proc.stdout is not None
        for line in proc.stdout:
            sys.stdout.write(line)
            log.write(line)
            tail = (tail + [line.rstrip()])[-5:]
    code = proc.wait()
    timed_out = not timer.is_alive() and code != 0
    timer.cancel()
    leaked = reap_leftovers(env["OSMO_BENCH_RUN"])
    seconds = time.perf_counter() - t0
    record = {"script": name, "path": str(script), "seconds": round(seconds, 1),
              "log": str(log_path), "status": "ok", "leftover_processes": leaked,
              "loadavg_1m": [round(load_before, 2), round(os.getloadavg()[0], 2)]}
    if leaked:
        print(f"!! {name} left {len(leaked)} process(es) running (killed): {leaked}", flush=True)
    rows: list[Row] = []
    problem = ""
    try:  # a script that failed part-way may still have written the rows it has
        rows = validate(json.loads(Path(json_path).read_text() or "null"))
    except (ValueError, TypeError) as exc:
        problem = f"bad --json output: {exc}"
    if code != 0:
        problem = f"timed out after {timeout:.0f} s" if timed_out else f"exit code {code}"
    Path(json_path).unlink(missing_ok=True)
    if not problem and not rows:  # e.g. bench_datagen without the sim extra
        record["status"] = "skipped"
        record["error"] = next((line for line in reversed(tail) if line.strip()), "")[:200]
    for r in rows:
        r["script"] = name
    if problem:
        record["status"] = "failed"
        last = next((line for line in reversed(tail) if line.strip()), "")
        record["error"] = f"{problem}; last output: {last[:200]}"
        rows += [{"name": f"{name}: FAILED", "script": name, "status": "failed", "unit": "",
                 "median": None, "min": None, "max": None, "runs": 0, "higher_is_better": True,
                 "notes": f"{record['error']} (log: {log_path})"}]
        print(f"!! {name} failed: {record['error']}", flush=True)
    return record, rows


def reap_leftovers(token: str) -> list[str]:
    """Kill (by pid) processes a finished script left behind, e.g. a server it did not stop.

    Every process the harness starts inherits ``OSMO_BENCH_RUN=<token>``; one still alive
    after its script exited is a leak, reported in the script's record.
    """
    mark = f"OSMO_BENCH_RUN={token}".encode()
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        try:
            if mark in (proc / "environ").read_bytes().split(b"\0"):
                cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode()
                os.kill(int(proc.name), signal.SIGKILL)
                found.append(f"{proc.name} {cmd[:100]}")
        except (OSError, ProcessLookupError):
            continue
    return found


def validate(data: object) -> list[Row]:
    """Check a script's rows against the protocol; raise ValueError naming the problem."""
    if not isinstance(data, list):
        raise ValueError("expected a JSON list of rows")
    for r in data:
        if not isinstance(r, dict):
            raise ValueError(f"a row is not an object: {r!r}")
        for key, kind in REQUIRED.items():
            if not isinstance(r.get(key), kind):
                raise ValueError(f"row {r.get('name')!r}: '{key}' missing or not {kind}")
        for key in ("limit", "target"):
            if key in r and not isinstance(r[key], (int, float)):
                raise ValueError(f"row {r['name']!r}: '{key}' is not a number")
        r.setdefault("status", "ok")
    return data


def resolve_limits(rows: list[Row]) -> None:
    """Fill ``limit`` from ``limit_of``/DEFAULT_LIMITS; add ``fraction_of_limit``."""
    by_name = {r["name"]: r for r in rows if r["status"] == "ok"}
    for r in rows:
        if r["status"] != "ok" or r["name"].startswith("limit:"):
            continue
        ref = r.get("limit_of") or next(
            (lim for pattern, lim in DEFAULT_LIMITS if pattern.search(r["name"])), None)
        if "limit" not in r and ref in by_name and by_name[ref]["unit"] == r["unit"]:
            r["limit"] = by_name[ref]["median"]
        if r.get("limit") and r["median"]:
            ratio = r["median"] / r["limit"]
            r["fraction_of_limit"] = ratio if r["higher_is_better"] else 1 / ratio


def derive(rows: list[Row]) -> list[Row]:
    """Rows computed from others: the engine's overhead per task over the spawn limit."""
    by_name = {r["name"]: r for r in rows if r["status"] == "ok"}
    fan = next((r for r in rows if r["status"] == "ok"
                and re.match(r"^osmo fan-out/join [\d,]+ `true` tasks$", r["name"])), None)
    spawn = by_name.get(SPAWN)
    if fan is None or spawn is None:
        return []
    limit_ms = 1000 / spawn["median"]

    def overhead(tasks_s: float) -> float:
        return 100 * ((1000 / tasks_s) / limit_ms - 1)
    values = [overhead(fan[k]) for k in ("median", "min", "max")]
    return [{"name": f"derived: {fan['name'][5:]}: time per task above the spawn limit's",
             "unit": "%", "median": values[0], "min": min(values), "max": max(values),
             "runs": fan["runs"], "higher_is_better": False, "target": 50.0, "status": "ok",
             "script": "suite",
             "notes": f"{1000 / fan['median']:.2f} ms/task vs {limit_ms:.2f} ms/task spawning "
                      "`true` (min/max from the fan-out's min/max)"}]


def check_targets(rows: list[Row]) -> None:
    """Set ``pass`` on every row with a target."""
    for r in rows:
        if r["status"] == "ok" and "target" in r:
            r["pass"] = (r["median"] >= r["target"] if r["higher_is_better"]
                         else r["median"] <= r["target"])


def num(x: float | None) -> str:
    """A number in a few significant digits, with thousands separators."""
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "—"
    a = abs(x)
    if a >= 100:
        return f"{x:,.0f}"
    if a >= 10:
        return f"{x:.1f}"
    if a >= 1:
        return f"{x:.2f}"
    return f"{x:.3f}"


def markdown(machine: dict[str, Any], scripts: list[dict[str, Any]], rows: list[Row],
             quick: bool) -> str:
    """The report: machine, targets, then every row grouped by script."""
    smoke = " (quick smoke run: sizes are tiny, numbers mean nothing)" if quick else ""
    lines = [f"# osmo benchmarks{smoke}",
             "",
             f"{machine['date']} · {machine['cpu']} · {machine['cores']} cores · "
             f"Python {machine['python']} · {machine['kernel']} · load average at start "
             f"{machine['loadavg_1m_at_start']}, at the end {machine.get('loadavg_1m_at_end')}",
             "", "Medians of the runs, with min–max. \"of limit\": the figure as a fraction of "
             "the machine's own limit (100% = nothing added).", ""]
    targeted = [r for r in rows if "pass" in r]
    if targeted:
        lines += ["## Targets", "", "| target | median (min–max) | wanted | result |",
                  "|---|---|---|---|"]
        for r in targeted:
            op = "≥" if r["higher_is_better"] else "≤"
            lines.append(f"| {r['name']} | {num(r['median'])} {r['unit']} "
                         f"({num(r['min'])}–{num(r['max'])}) | {op} {num(r['target'])} "
                         f"{r['unit']} | {'**pass**' if r['pass'] else '**FAIL**'} |")
        lines.append("")
    lines += ["## All rows", "", "| benchmark | median | min–max | unit | runs | limit | of limit "
              "| notes |", "|---|---|---|---|---|---|---|---|"]
    for s in scripts:
        failed = {"ok": "", "skipped": f", skipped: {s.get('error', '')}"}.get(
            s["status"], ", FAILED")
        load = "load {} → {}".format(*s["loadavg_1m"]) if "loadavg_1m" in s else ""
        lines.append(f"| **{s['script']}** ({s['seconds']:.0f} s{failed}) | | | | | | | "
                     f"{load} |")
        for r in (r for r in rows if r["script"] == s["script"]):
            frac = r.get("fraction_of_limit")
            notes = str(r.get("notes", "")).replace("|", "\\|")
            lines.append(f"| {r['name']} | {num(r['median'])} | {num(r['min'])}–{num(r['max'])} "
                         f"| {r['unit']} | {r['runs']} | {num(r.get('limit'))} | "
                         f"{'' if frac is None else f'{100 * frac:.0f}%'} | {notes} |")
    derived = [r for r in rows if r["script"] == "suite"]
    for r in derived:
        lines.append(f"| {r['name']} | {num(r['median'])} | {num(r['min'])}–{num(r['max'])} "
                     f"| {r['unit']} | {r['runs']} | | | {r.get('notes', '')} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    """Parse arguments, run the scripts, write the report; exit 1 if a script failed."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: tiny sizes, one run each")
    ap.add_argument("--peers", action="store_true",
                    help="also compare with Prefect and Ray (installs them into "
                         ".cache/bench-peers-venv)")
    ap.add_argument("--only", help="run only scripts whose name matches this regex "
                                   "(the peer comparison is called 'peers')")
    ap.add_argument("--out", default=str(HERE / "results"), help="results folder")
    ap.add_argument("--scripts", default=str(HERE), help="folder of bench_*.py scripts")
    ap.add_argument("--timeout", type=float, default=None,
                    help="seconds per script (default 900, quick 360)")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    timeout = args.timeout or (360.0 if args.quick else 900.0)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    # every osmo CLI, server and worker a script starts is a new interpreter: without its
    # bytecode cache each one compiles osmo again (~75 ms a CLI), where a peer's long-lived
    # workers compile once; a user's machine writes the cache, so the benchmarks do too
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env.pop("OSMO_SERVER", None)
    env.pop("OSMO_HOME", None)
    env["OSMO_BENCH_RUN"] = f"{os.getpid()}-{time.time_ns()}"
    if args.quick:
        env["OSMO_BENCH_QUICK"] = "1"
    if args.peers:  # scripts that compare with a peer themselves (bench_sim.py) run it too
        env["OSMO_BENCH_PEERS"] = "1"
    machine = machine_info()
    scripts = sorted(Path(args.scripts).glob("bench_*.py"))
    if args.peers:
        scripts.append(HERE / "peers" / "compare.py")
    if args.only:
        scripts = [s for s in scripts if re.search(args.only, "peers" if s.parent.name == "peers"
                                                   else s.stem)]
    records, rows = [], []
    for script in scripts:
        record, script_rows = run_script(script, out, env, timeout)
        records.append(record)
        rows += script_rows
    machine["loadavg_1m_at_end"] = round(os.getloadavg()[0], 2)
    resolve_limits(rows)
    rows += derive(rows)
    check_targets(rows)
    report = {"machine": machine, "quick": args.quick, "peers": args.peers,
              "scripts": records, "rows": rows}
    (out / "latest.json").write_text(json.dumps(report, indent=2, ensure_ascii=False) + "\n")
    (out / "latest.md").write_text(markdown(machine, records, rows, args.quick))
    print(f"\nwrote {out / 'latest.md'} and {out / 'latest.json'}")
    failed = [r["script"] for r in records if r["status"] == "failed"]
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
