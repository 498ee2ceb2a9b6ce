"""The base of every task's environment (pure logic; end to end in tests/e2e/test_tasktypes.py)."""

from __future__ import annotations

from osmo.worker.taskenv import DEFAULT_PATH, base_env, with_threads


def test_the_base_takes_only_the_documented_variables_and_osmos_defaults() -> None:
    env = base_env({"PATH": "/p", "HOME": "/h", "OSMO_HOME": "/secret", "AWS_SECRET": "x"})
    assert env == {"PATH": "/p", "HOME": "/h", "OMP_WAIT_POLICY": "PASSIVE"}
    assert base_env({})["PATH"] == DEFAULT_PATH


def test_the_workers_own_wait_policy_replaces_osmos_default() -> None:
    assert base_env({"OMP_WAIT_POLICY": "ACTIVE"})["OMP_WAIT_POLICY"] == "ACTIVE"


def test_a_cpu_request_sets_the_thread_count_unless_the_task_or_worker_does() -> None:
    assert with_threads({"PATH": "/p"}, 2) == {"PATH": "/p", "OMP_NUM_THREADS": "2"}
    assert with_threads({}, 0) == {"OMP_NUM_THREADS": "1"}  # a cpu request of 0: one
    assert with_threads({}, None) == {}  # no request: the libraries' own default
    assert with_threads({"OMP_NUM_THREADS": "7"}, 2) == {"OMP_NUM_THREADS": "7"}
    assert base_env({"OMP_NUM_THREADS": "3"})["OMP_NUM_THREADS"] == "3"  # the worker's
