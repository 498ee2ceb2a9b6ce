"""Progress bars of transfers over a few MB, seen through a pseudo-terminal, and never in a pipe.

The client plays another machine (``OSMO_HOST_ID``), so the bytes come over the network path
(zenoh, sealed) as they would from a remote server, not as same-host hard links.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.cli.terminal import in_pty
from tests.conftest import REPO, Osmo, write

BIG = 6 * 2**20  # over the 4 MiB threshold
RATE = re.compile(r"\d+(\.\d+)? ?[kMG]?B/s")
BAR = "━"  # rich's bar


@pytest.fixture
def remote(osmo: Osmo) -> dict[str, str]:
    """A running server, and the environment of a client that is on another machine."""
    osmo("server", "start", check=True)  # started without the client's host id
    return dict(osmo.env, OSMO_HOST_ID="another-machine")


def _forget_fetched(osmo: Osmo) -> None:
    """Empty the client's cache, so the next command fetches every byte again."""
    shutil.rmtree(osmo.home / "client" / "artifacts", ignore_errors=True)


def test_artifacts_get_shows_a_bar_with_a_rate_on_a_terminal_only(
        osmo: Osmo, remote: dict[str, str], tmp_path: Path) -> None:
    spec = write(tmp_path / "big.yaml", f"""
workflow:
  name: big
  tasks:
  - name: make
    command: ["sh", "-c", "head -c {BIG} /dev/urandom > {{{{output}}}}/big.bin"]
""")
    wf = osmo.submit(spec, "--wait")
    code, out = in_pty("artifacts", "get", f"{wf}:make", "-o", str(tmp_path / "a"),
                        env=remote)
    assert code == 0, out
    assert (tmp_path / "a" / "big.bin").stat().st_size == BIG
    assert BAR in out and RATE.search(out), out  # a bar, with a rate
    assert "6.3 MB" in out or "6.3/6.3 MB" in out, out

    _forget_fetched(osmo)
    piped = subprocess.run([sys.executable, "-m", "osmo", "artifacts", "get", f"{wf}:make",
                            "-o", str(tmp_path / "b")], env=remote, cwd=REPO,
                           capture_output=True, text=True, timeout=120)
    assert piped.returncode == 0, piped.stderr
    assert piped.stdout == f"{tmp_path / 'b' / 'big.bin'}\n" and piped.stderr == ""


def test_dataset_upload_and_download_show_bars_on_a_terminal(osmo: Osmo, remote: dict[str, str],
                                                            tmp_path: Path) -> None:
    folder = tmp_path / "data"
    folder.mkdir()
    (folder / "big.bin").write_bytes(os.urandom(BIG))
    code, out = in_pty("dataset", "upload", "bigset", str(folder), env=remote)
    assert code == 0 and "bigset:1" in out, out
    assert BAR in out and RATE.search(out), out
    _forget_fetched(osmo)
    code, out = in_pty("dataset", "download", "bigset", "-o", str(tmp_path / "d"),
                        env=remote)
    assert code == 0, out
    assert (tmp_path / "d" / "big.bin").read_bytes() == (folder / "big.bin").read_bytes()
    assert BAR in out and RATE.search(out), out


def test_a_small_transfer_shows_no_bar(osmo: Osmo, remote: dict[str, str],
                                       tmp_path: Path) -> None:
    folder = tmp_path / "small"
    folder.mkdir()
    (folder / "s.txt").write_text("small\n")
    code, out = in_pty("dataset", "upload", "smallset", str(folder), env=remote)
    assert code == 0 and "smallset:1" in out and BAR not in out, out
