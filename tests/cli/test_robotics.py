"""``osmo eval report`` and ``osmo view`` on local files (no server needed).

The report here is ``sim.eval``'s leaderboard (``osmo_plugins.sim.report``), found and shown as
any task type's report is (``osmo.tasktypes.reports``).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from osmo.cli.main import main


def _metrics(path: Path, results: list[tuple[str, str, float]]) -> Path:
    rows = [{"policy": p, "kind": p, "env": env, "episodes": 3, "success_rate": ret / 1000,
             "success_criterion": "return >= 500 (workflow params)",
             "mean_return": ret, "return_ci95": [ret - 1, ret + 1], "mean_length": ret,
             "normalized_score": None, "normalized_ci95": None,
             "returns": [ret] * 3, "seeds": [1, 2, 3]} for p, env, ret in results]
    path.write_text(json.dumps({"suite": {"envs": [], "seeds": [1, 2, 3]}, "results": rows}))
    return path


def test_report_from_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a = _metrics(tmp_path / "a.json", [("train", "Pend-v5", 1000.0), ("random", "Pend-v5", 8.0)])
    b = _metrics(tmp_path / "b.json", [("expert", "Pend-v5", 999.0)])
    assert main(["eval", "report", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if "Pend-v5" in ln]
    assert [ln.split()[2] for ln in lines] == ["train", "expert", "random"]
    assert "1000.0 [999.0, 1001.0]" in out
    # 3 episodes: 100% has a Wilson interval of [44, 100], 1% (0 of 3 rounded) of [0, 56]
    assert "100% [44, 100] [1]" in lines[0] and "1% [0, 56] [1]" in lines[2]
    assert "[1] return >= 500 (workflow params)" in out
    assert main(["eval", "report", str(a), "--format", "json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert [r["policy"] for r in got] == ["train", "random"]
    assert [round(100 * x) for x in got[0]["success_ci95"]] == [44, 100]


def test_report_shows_na_criteria_and_normalised(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """No criterion → n/a, never a number; each criterion is a footnote (issue 20)."""
    rows = [
        {"policy": "random", "kind": "random", "env": "HalfCheetah-v5", "episodes": 2,
         "success_rate": None, "success_criterion": "n/a: no success signal",
         "mean_return": -125.6, "return_ci95": [-130.0, -120.0], "mean_length": 1000,
         "normalized_score": None},
        {"policy": "expert", "kind": "expert", "env": "Pend-v5", "episodes": 2,
         "success_rate": 1.0, "success_criterion": "info['is_success'] (the env's own)",
         "mean_return": 50.0, "return_ci95": [50.0, 50.0], "mean_length": 50,
         "normalized_score": 1.0, "normalized_ci95": [1.0, 1.0]},
        {"policy": "random", "kind": "random", "env": "Pend-v5", "episodes": 2,
         "success_rate": 0.0, "success_criterion": "info['is_success'] (the env's own)",
         "mean_return": 5.0, "return_ci95": [4.0, 6.0], "mean_length": 5,
         "normalized_score": 0.0, "normalized_ci95": [-0.02, 0.02]}]
    path = tmp_path / "m.json"
    path.write_text(json.dumps({"suite": {"envs": []}, "results": rows}))
    assert main(["eval", "report", str(path)]) == 0
    out = capsys.readouterr().out
    cheetah = next(ln for ln in out.splitlines() if "HalfCheetah" in ln)
    assert "n/a [1]" in cheetah and "%" not in cheetah
    assert "[1] n/a: no success signal" in out
    assert "[2] info['is_success'] (the env's own)" in out
    expert = next(ln for ln in out.splitlines() if "expert" in ln)
    assert "100% [34, 100] [2]" in expert and " 1.00 " in expert
    assert main(["eval", "report", str(path), "--format", "json"]) == 0
    got = {r["policy"] + r["env"]: r for r in json.loads(capsys.readouterr().out)}
    assert got["randomHalfCheetah-v5"]["success_rate"] is None
    assert got["randomPend-v5"]["normalized_score"] == 0.0


def test_report_reads_metrics_from_before_issue_20(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    row = {"policy": "random", "kind": "random", "env": "Pend-v5", "episodes": 2,
           "success_rate": 0.0, "mean_return": 5.0, "return_ci95": [4.0, 6.0],
           "mean_length": 5}
    path = tmp_path / "old.json"
    path.write_text(json.dumps({"suite": {"success": "ran max_steps steps without terminating"},
                                "results": [row]}))
    assert main(["eval", "report", str(path)]) == 0
    assert "[1] ran max_steps steps without terminating (older sim.eval)" in \
        capsys.readouterr().out


def test_report_rejects_other_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "x.json"
    bad.write_text("{}")
    assert main(["eval", "report", str(bad)]) == 2
    assert "not a sim.eval metrics.json" in capsys.readouterr().err


def test_view_local_mcap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("rerun")
    pytest.importorskip("numpy")
    pytest.importorskip("foxglove")
    from osmo_plugins.episodes import EpisodeWriter

    src = tmp_path / "ep.mcap"
    with EpisodeWriter(src, {"env": "Fake-v0"}, dt=0.1) as w:
        w.step(0, 0, [0.0, 1.0], [0.5, 0.0], 1.0, False, True)
        w.end(0, 1, 1.0, 1, False, True)
    out = tmp_path / "x.rrd"
    assert main(["view", str(src), "--out", str(out)]) == 0
    assert out.stat().st_size > 0 and f"wrote {out}" in capsys.readouterr().out


def test_view_a_run_record(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A run record (foxglove.Log on /osmo/log, JSON status and lineage) converts too."""
    pytest.importorskip("rerun")
    from osmo.record import write_run_record

    src = tmp_path / "run.mcap"
    write_run_record(src, workflow={"id": "wf-1", "name": "wf", "status": "COMPLETED"},
                     transitions=[{"at": 1.0, "task": "a", "retry": 0, "status": "RUNNING"}],
                     lineage=[], logs=[{"ts": 1.5, "task": "a", "retry": 0,
                                        "stream": "stdout", "text": "hello"}])
    out = tmp_path / "run.rrd"
    assert main(["view", str(src), "--out", str(out)]) == 0
    assert out.stat().st_size > 0 and f"wrote {out}" in capsys.readouterr().out


def test_report_escapes_hostile_names(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Names in metrics files are data: they cannot clear the screen or forge a line."""
    path = _metrics(tmp_path / "m.json", [("evil\x1b[2J\nrandom  Pend-v5  1", "Pend-v5", 5.0)])
    data = json.loads(path.read_text())
    data["results"][0]["success_criterion"] = "return >= 1\x1b]0;pwned\x07"
    path.write_text(json.dumps(data))
    assert main(["eval", "report", str(path)]) == 0
    out = capsys.readouterr().out
    assert "\x1b" not in out and "\x07" not in out
    assert "evil\\033[2J\\nrandom" in out and "\\033]0;pwned\\a" in out
    assert len([ln for ln in out.splitlines() if "Pend-v5" in ln]) == 1
