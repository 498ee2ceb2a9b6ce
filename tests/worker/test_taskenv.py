"""The base of every task's environment (pure logic; end to end in tests/e2e/test_tasktypes.py)."""

from __future__ import annotations

from osmo.worker.taskenv import DEFAULT_PATH, base_env


def test_the_base_takes_only_the_documented_variables_and_osmos_defaults() -> None:
    env = base_env({"PATH": "/p", "HOME": "/h", "OSMO_HOME": "/secret", "AWS_SECRET": "x"})
    assert env == {"PATH": "/p", "HOME": "/h", "OMP_WAIT_POLICY": "PASSIVE"}
    assert base_env({})["PATH"] == DEFAULT_PATH


def test_the_workers_own_wait_policy_replaces_osmos_default() -> None:
    assert base_env({"OMP_WAIT_POLICY": "ACTIVE"})["OMP_WAIT_POLICY"] == "ACTIVE"
