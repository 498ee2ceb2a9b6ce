"""The conformance kit on good and deliberately broken task types."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from osmo import Param, task_type
from osmo.testing import check_task_type


@task_type(version="1", params={"n": Param(int, default=2, min=1)})
def good(ctx: Any) -> None:
    """Writes n lines and an MCAP."""
    data = "".join(f"{i}\n" for i in range(ctx.params["n"]))
    (ctx.output / "lines.txt").write_text(data + (ctx.inputs[0] / "x").read_text())
    with ctx.mcap_writer("rec.mcap"):
        pass


class NoOutput:
    name, version, description, extra = "quiet", "1", "", None
    params: dict[str, Param] = {}
    resources: dict[str, Any] = {}

    def run(self, ctx: Any) -> None:
        pass


class BadShape(NoOutput):
    version = 2  # type: ignore[assignment]
    params = {"n": Param(int, default="two")}  # type: ignore[dict-item]

    def run(self) -> None:  # type: ignore[override]
        pass


@task_type(version="1")
def crashes(ctx: Any) -> None:
    raise RuntimeError("boom")


def test_good_type_passes_and_reports_its_files(tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "x").write_text("end")
    files = check_task_type(good, {"n": 3}, inputs=[tmp_path / "in"], workdir=tmp_path / "w")
    assert files == ["lines.txt", "rec.mcap"]
    assert (tmp_path / "w" / "output" / "lines.txt").read_text() == "0\n1\n2\nend"


@pytest.mark.parametrize(("obj", "params", "messages"), [
    (BadShape, {}, ["'version' must be a string, got 2",
                    "param 'n': its default must be int, got str 'two'",
                    "'run' must take exactly one argument (ctx)"]),
    (good, {"n": 0, "m": 1}, ["param 'm' is not declared (declared: n)",
                              "param 'n' must be at least 1; got 0"]),
    (NoOutput, {}, ["run(ctx) wrote nothing under ctx.output"]),
    (crashes, {}, ["run(ctx) raised RuntimeError: boom"]),
])
def test_broken_types_fail_with_precise_messages(obj: Any, params: dict[str, Any],
                                                 messages: list[str]) -> None:
    with pytest.raises(AssertionError) as err:
        check_task_type(obj, params)
    for message in messages:
        assert message in str(err.value)
