"""``osmo eval report`` and ``osmo view`` on local files (no server needed)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from osmo.cli.main import main
from osmo.cli.robotics import leaderboard_rows


def _metrics(path: Path, results: list[tuple[str, str, float]]) -> Path:
    rows = [{"policy": p, "kind": p, "env": env, "episodes": 3, "success_rate": ret / 100,
             "mean_return": ret, "return_ci95": [ret - 1, ret + 1], "mean_length": ret,
             "returns": [ret] * 3, "seeds": [1, 2, 3]} for p, env, ret in results]
    path.write_text(json.dumps({"suite": {"envs": [], "seeds": [1, 2, 3]}, "results": rows}))
    return path


def test_rows_rank_per_env() -> None:
    sources = [("wf-1", "eval", {"results": [
        {"policy": "random", "kind": "random", "env": "A", "episodes": 2, "success_rate": 0.0,
         "mean_return": 5.0, "return_ci95": [4, 6], "mean_length": 5},
        {"policy": "train", "kind": "checkpoint", "env": "A", "episodes": 2,
         "success_rate": 1.0, "mean_return": 90.0, "return_ci95": [80, 100], "mean_length": 90},
        {"policy": "random", "kind": "random", "env": "B", "episodes": 2, "success_rate": 0.0,
         "mean_return": 1.0, "return_ci95": [0, 2], "mean_length": 1}]})]
    rows = leaderboard_rows(sources)
    assert [(r["env"], r["rank"], r["policy"]) for r in rows] == [
        ("A", 1, "train"), ("A", 2, "random"), ("B", 1, "random")]


def test_report_from_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a = _metrics(tmp_path / "a.json", [("train", "Pend-v5", 1000.0), ("random", "Pend-v5", 8.0)])
    b = _metrics(tmp_path / "b.json", [("expert", "Pend-v5", 999.0)])
    assert main(["eval", "report", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if "Pend-v5" in ln]
    assert [ln.split()[2] for ln in lines] == ["train", "expert", "random"]
    assert "1000.0 [999.0, 1001.0]" in out
    assert main(["eval", "report", str(a), "--format", "json"]) == 0
    assert [r["policy"] for r in json.loads(capsys.readouterr().out)] == ["train", "random"]


def test_report_rejects_other_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "x.json"
    bad.write_text("{}")
    assert main(["eval", "report", str(bad)]) == 2
    assert "not a sim.eval metrics.json" in capsys.readouterr().err


def test_view_local_mcap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("rerun")
    pytest.importorskip("numpy")
    from osmo_plugins.episodes import EpisodeWriter

    from osmo.record import LineageMcapWriter

    src = tmp_path / "ep.mcap"
    with LineageMcapWriter(src, None) as mcap:
        w = EpisodeWriter(mcap, {"env": "Fake-v0"}, dt=0.1)
        w.step(0, 0, [0.0, 1.0], [0.5, 0.0], 1.0, False, True)
        w.end(0, 1, 1.0, 1, False, True)
    out = tmp_path / "x.rrd"
    assert main(["view", str(src), "--out", str(out)]) == 0
    assert out.stat().st_size > 0 and f"wrote {out}" in capsys.readouterr().out
