"""Arguments as OSMO's CLI takes them (pure parsing; the e2e test runs them through a server)."""

from __future__ import annotations

import argparse

import pytest

from osmo.cli.main import build_parser, main
from osmo.errors import UsageError


def parse(*argv: str) -> argparse.Namespace:
    from osmo.cli.main import _check_spec_file, _resolve_format

    args = build_parser().parse_args(argv)
    _resolve_format(args)
    _check_spec_file(args)
    return args


@pytest.mark.parametrize("verb", [("submit",), ("validate",), ("workflow", "submit")])
def test_set_flags_take_several_values_and_repeat(verb: tuple[str, ...]) -> None:
    args = parse(*verb, "wf.yaml", "--set", "greeting=hola", "count=3", "--set-string", "v=1",
                 "w=2", "--set", "count=4", "--set-env", "A=1", "B=2", "--set-env", "A=3")
    assert args.file == "wf.yaml"
    assert args.set_values == ["greeting=hola", "count=3", "count=4"]  # later wins when applied
    assert args.set_strings == ["v=1", "w=2"]
    assert args.set_env == ["A=1", "B=2", "A=3"]


@pytest.mark.parametrize("flag", ["--set", "--set-string", "--set-env"])
def test_a_spec_file_swallowed_by_a_set_flag_names_the_fix(flag: str) -> None:
    with pytest.raises(UsageError) as err:
        parse("submit", flag, "a=1", "b=2", "wf.yaml")
    assert str(err.value) == (f"no workflow spec file: {flag} takes every K=V after it, and it "
                              f"took 'wf.yaml'. Put the file first: osmo submit wf.yaml {flag} "
                              "a=1 b=2")


def test_no_spec_file_at_all_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["validate"]) == 2
    assert "no workflow spec file" in capsys.readouterr().err


@pytest.mark.parametrize("argv, server, fmt", [
    (["--server", "tcp/h:1", "-t", "json", "query", "X"], "tcp/h:1", "json"),
    (["query", "X", "--server", "tcp/h:1", "--format", "json"], "tcp/h:1", "json"),
    (["--server", "tcp/a:1", "query", "X", "--server", "tcp/b:2"], "tcp/b:2", "text"),
    (["--format", "json", "workflow", "query", "X"], None, "json"),
    (["-t", "json", "query", "X", "-t", "text"], None, "text"),  # the verb's own wins
    (["query", "X"], None, "text"),
    (["lineage", "X"], None, "text"),
    (["--format", "dot", "lineage", "X"], None, "dot"),
    (["dataset", "list", "--server", "tcp/h:1"], "tcp/h:1", "text"),
])
def test_global_options_before_or_after_the_verb(argv: list[str], server: str | None,
                                                 fmt: str) -> None:
    args = parse(*argv)
    assert (args.server, args.format) == (server, fmt)


def test_a_global_format_the_verb_does_not_have_is_refused() -> None:
    with pytest.raises(UsageError, match="'dot' is not one of text, json"):
        parse("-t", "dot", "query", "X")


def test_after_the_verb_its_own_short_options_keep_their_meaning() -> None:
    args = parse("logs", "X", "-t", "train", "--error", "--server", "tcp/h:1")
    assert (args.task, args.error, args.server) == ("train", True, "tcp/h:1")


def test_cancel_takes_several_ids() -> None:
    assert parse("cancel", "a-1", "b-2").workflow_ids == ["a-1", "b-2"]
    assert parse("workflow", "cancel", "a-1").workflow_ids == ["a-1"]
