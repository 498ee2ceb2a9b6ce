"""viz.rerun: episode MCAP and any other MCAP → .rrd."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("numpy")
pytest.importorskip("rerun")

from osmo_plugins.episodes import EpisodeWriter  # noqa: E402
from osmo_plugins.viz.rerun_view import RERUN  # noqa: E402

from osmo.record import LineageMcapWriter  # noqa: E402
from tests.plugins.fakectx import make_ctx  # noqa: E402


def _inputs(tmp: Path) -> Path:
    folder = tmp / "in"
    with EpisodeWriter(folder / "episodes.mcap", {"env": "Fake-v0"}, dt=0.1) as w:
        for t in range(4):
            w.step(0, t, [t, 0.0], [0.5, 0.1], 1.0, False, t == 3)
        w.end(0, 1, 4.0, 4, False, True)
    with LineageMcapWriter(folder / "other.mcap", None) as mcap:
        ch = mcap.add_json_channel("/x", "X", {"type": "object"})
        mcap.write(ch, {"x": 1})
    return folder


def test_one_rrd_per_mcap(tmp_path: Path) -> None:
    ctx = make_ctx(RERUN, tmp_path, "viz", inputs=[_inputs(tmp_path)])
    RERUN.run(ctx)
    got = sorted(p.name for p in ctx.output.iterdir())
    assert got == ["episodes.rrd", "other.rrd"]
    assert all((ctx.output / name).read_bytes()[:4] == b"RRF2" for name in got)


def test_combined(tmp_path: Path) -> None:
    ctx = make_ctx(RERUN, tmp_path, "viz", inputs=[_inputs(tmp_path)], combine=True)
    RERUN.run(ctx)
    assert [p.name for p in ctx.output.iterdir()] == ["combined.rrd"]


def test_no_files(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no files matching"):
        RERUN.run(make_ctx(RERUN, tmp_path, "viz", inputs=[tmp_path / "empty"]))
