"""LocalPool in the sandbox: a start whose sandbox cannot be set up is an infrastructure error.

The command's own exit code is never confused with bubblewrap's (tests/runtime/churn.py
makes the setup fail for a moment; tests/e2e/test_sandbox_setup.py retries it end to end).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.layout import Home
from osmo.scheduler.types import (
    LOCAL_NODE,
    AttemptExited,
    AttemptStarted,
    AttemptStartFailed,
    KillAttempt,
)
from osmo.worker.pool import KILLED_BEFORE_START, LocalPool
from osmo.worker.starts import SETUP_TRIES
from tests.runtime.churn import churning_mounts
from tests.worker.test_pool import Events, attempt_dir, log_of, sh, submit, wait_until


@pytest.fixture
def events() -> Events:
    return Events()


@pytest.fixture
def boxed(tmp_path: Path, events: Events) -> Iterator[LocalPool]:
    pool = LocalPool(home=Home(tmp_path / "home"), emit=events, kill_grace=0.5, sandbox="on")
    yield pool
    pool.close()


def test_a_sandbox_that_never_sets_up_fails_the_start(boxed: LocalPool, events: Events) -> None:
    """bwrap cannot make a tmpfs on a folder missing from a read-only system folder: every
    try fails."""
    boxed.hide(Path(f"/usr/osmo-missing-{os.getpid()}"))
    aid = submit(boxed, sh("ok", "echo ran > {{output}}/ran"))
    final = events.final(aid)
    assert isinstance(final, AttemptStartFailed), final
    assert "sandbox could not be set up" in final.message
    assert "bwrap: Can't mkdir" in final.message, final.message
    retries = [text for stream, text in log_of(boxed, aid)
               if stream == "osmo" and "trying again" in text]
    assert len(retries) == SETUP_TRIES - 1, log_of(boxed, aid)
    assert events.of(aid).count(AttemptStarted) == SETUP_TRIES  # each try's pid recorded
    folder = attempt_dir(boxed, aid)
    assert folder is not None and not (folder / "output").exists()


def test_a_setup_that_fails_for_a_moment_is_retried(boxed: LocalPool, events: Events) -> None:
    """Under heavy mount churn some tries fail; each attempt still runs its command once."""
    with churning_mounts(count=60):
        ids = [submit(boxed, sh(f"t{i}", "echo ran >> {{output}}/ran; exit 0"))
               for i in range(60)]
        finals = [events.final(aid) for aid in ids]
    assert all(isinstance(f, AttemptExited) and f.exit_code == 0 and f.output for f in finals), [
        f for f in finals if not isinstance(f, AttemptExited) or f.exit_code]
    for final in finals:
        assert isinstance(final, AttemptExited) and final.output is not None
        assert (Path(final.output) / "ran").read_text() == "ran\n"  # once, not per try
    assert any(any("trying again" in text for _, text in log_of(boxed, aid)) for aid in ids)


def test_a_kill_between_tries_ends_the_attempt_once(boxed: LocalPool, events: Events) -> None:
    boxed.hide(Path(f"/usr/osmo-missing-{os.getpid()}"))
    aid = submit(boxed, sh("ok", "exit 0"))
    events.wait_for(lambda e: isinstance(e, AttemptStarted) and e.attempt_id == aid)
    wait_until(lambda: any("trying again" in text for _, text in log_of(boxed, aid)))
    boxed.kill(KillAttempt(aid, LOCAL_NODE, "canceled"))
    final = events.final(aid)
    assert isinstance(final, AttemptExited) and final.exit_code == KILLED_BEFORE_START, final
    assert final.output is None and final.message == "killed: canceled"
    time.sleep(0.7)  # every pending try would have come by now: none starts, no second report
    assert events.of(aid).count(AttemptExited) + events.of(aid).count(AttemptStartFailed) == 1
