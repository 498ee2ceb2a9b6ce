"""Kubernetes-style ``$(NAME)`` expansion (pure; the e2e test runs it through a task's args)."""

from __future__ import annotations

import pytest

from osmo.spec.tokens import expand_vars

ENV = {"A": "1", "B": "two words", "EMPTY": "", "REF": "$(A)"}


@pytest.mark.parametrize("text, expected", [
    ("$(A)", "1"),
    ("x$(A)y$(B)z", "x1ytwo wordsz"),
    ("$(EMPTY)|", "|"),
    ("$(UNDEFINED)", "$(UNDEFINED)"),     # kept as written
    ("$$(A)", "$(A)"),                    # the escape
    ("$$$(A)", "$1"),
    ("$$", "$"),
    ("echo $$ $HOME ${A}", "echo $ $HOME ${A}"),  # shell syntax other than $( is kept
    ("$(A", "$(A"),                       # unclosed
    ("end $", "end $"),
    ("$(REF)", "$(A)"),                   # one pass: values are not expanded again
    ("no dollars", "no dollars"),
    ("$()", "$()"),
])
def test_expand_vars(text: str, expected: str) -> None:
    assert expand_vars(text, ENV) == expected
