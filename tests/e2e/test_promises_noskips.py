"""README: `./dev test` runs the whole suite and nothing may skip (tests/conftest.py enforces
it when OSMO_NO_SKIPS=1). These run pytest on a small suite that uses the same hooks."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from tests.conftest import REPO

SUITE = '''
import pytest

def test_passes():
    pass

def test_skips():
    pytest.skip("a tool is missing")

@pytest.mark.skipif(True, reason="marked to skip")
def test_marked():
    pass

@pytest.mark.xfail(strict=True, reason="a documented bug")
def test_expected_failure():
    assert False
'''

MODULE_SKIP = '''
import pytest
pytest.importorskip("no_such_module_anywhere")

def test_never_collected():
    pass
'''


HOOKS = ("from tests.conftest import (pytest_make_collect_report, pytest_runtest_makereport,\n"
         "    pytest_sessionfinish, pytest_terminal_summary)\n")


def _pytest(folder: Path, *, no_skips: bool, conftest: str = HOOKS
            ) -> subprocess.CompletedProcess[str]:
    (folder / "conftest.py").write_text(conftest)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get(
        "PYTHONPATH", "")]))
    env.pop("OSMO_NO_SKIPS", None)
    if no_skips:
        env["OSMO_NO_SKIPS"] = "1"
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-rA", "-p", "no:cacheprovider",
                           "--rootdir", str(folder), str(folder)], env=env, cwd=folder,
                          capture_output=True, text=True, timeout=120)


def test_a_full_run_fails_on_every_skip_but_not_on_xfail(tmp_path: Path) -> None:
    (tmp_path / "test_suite.py").write_text(SUITE)
    (tmp_path / "test_module_skip.py").write_text(MODULE_SKIP)
    relaxed = _pytest(tmp_path, no_skips=False)
    assert relaxed.returncode == 0, relaxed.stdout
    assert "1 passed, 3 skipped, 1 xfailed" in relaxed.stdout
    strict = _pytest(tmp_path, no_skips=True)
    assert strict.returncode == 1, strict.stdout
    # a skipped test fails (an error when it skipped in setup); a skipped module fails the run
    assert "1 failed, 1 passed, 1 skipped, 1 xfailed, 1 error" in strict.stdout, strict.stdout
    assert "skipped modules (not allowed in a full run)" in strict.stdout
    assert "a tool is missing" in strict.stdout and "marked to skip" in strict.stdout
    assert "no_such_module_anywhere" in strict.stdout
    assert "may not skip this" in strict.stdout and "ALLOWED_SKIPS" in strict.stdout


def test_only_a_skip_on_the_allow_list_passes(tmp_path: Path) -> None:
    (tmp_path / "test_suite.py").write_text(SUITE)
    allow = HOOKS + (
        "from tests import conftest\n"
        "conftest.ALLOWED_SKIPS += (\n"
        "    conftest.AllowedSkip('test_suite.py::test_skips', r'tool is missing'),\n"
        "    conftest.AllowedSkip('test_suite.py::test_marked', r'marked', when=False),\n"
        ")\n")
    r = _pytest(tmp_path, no_skips=True, conftest=allow)
    assert r.returncode == 1, r.stdout
    assert "1 passed, 1 skipped, 1 xfailed, 1 error" in r.stdout, r.stdout
    assert "SKIPPED [1] test_suite.py:8: a tool is missing" in r.stdout
    assert "ERROR test_suite.py::test_marked" in r.stdout  # its allowance does not hold here
