"""Same user by default: the home is private, another OS user is refused, and nothing listens
on the network without authentication unless told ``--insecure``.

Another uid is tried for real: the CLI runs as ``nobody`` against a home under a folder
``nobody`` may enter (so the refusal comes from the home's own protection, not from a
missing path). ``setpriv --reuid=nobody`` cannot start this machine's Python (its
``libpython`` lies under ``/root``, closed to other users), so the test process imports the
CLI first and then drops to ``nobody`` with ``setuid`` — the same switch setpriv makes.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from osmo.config import free_port, lock_is_held
from osmo.layout import Home
from tests.conftest import REPO, Osmo

NOBODY = 65534

AS_NOBODY = """
import os, sys, tempfile
from osmo.cli.main import main
assert main(["list"]) == 0  # as root first: every module the CLI needs is loaded now,
err, null = os.dup(2), os.open(os.devnull, os.O_WRONLY)  # the error path's too (quietly)
os.dup2(null, 2)
main(["--server", "tcp/127.0.0.1:9", "list"])
os.dup2(err, 2)
os.setgroups([]); os.setgid({uid}); os.setuid({uid})
home, sock = sys.argv[1], sys.argv[2]
print("list exit", main(["list"]), flush=True)
try:
    open(os.path.join(home, "state.db"), "rb")
    print("read state.db", flush=True)
except PermissionError:
    print("state.db closed", flush=True)
os.environ["OSMO_HOME"] = tempfile.mkdtemp()  # its own home; straight at the owner's socket
print("socket exit", main(["--server", "unixsock-stream/" + sock, "list"]), flush=True)
"""


@pytest.fixture
def shared_folder() -> Iterator[Path]:
    """A folder other users may enter (pytest's tmp_path is closed to them)."""
    base = Path(tempfile.mkdtemp(prefix="osmo-uid-"))
    os.chmod(base, 0o755)
    yield base
    shutil.rmtree(base, ignore_errors=True)


@pytest.mark.skipif(os.geteuid() != 0, reason="switching to another uid needs root")
def test_another_user_is_refused_and_cannot_read_the_home(shared_folder: Path) -> None:
    osmo = Osmo(shared_folder / "home")
    try:
        osmo("list", check=True)
        home = osmo.home
        assert stat.S_IMODE(home.stat().st_mode) == 0o700
        r = subprocess.run([sys.executable, "-c", AS_NOBODY.format(uid=NOBODY), str(home),
                            str(home / "server.sock")], env=osmo.env, cwd=REPO,
                           capture_output=True, text=True, timeout=120)
        assert "list exit 3" in r.stdout, (r.stdout, r.stderr)
        assert f"belongs to uid 0, not to you (uid {NOBODY})" in r.stderr
        assert "state.db closed" in r.stdout
        assert "socket exit 3" in r.stdout and "cannot connect" in r.stderr
        assert "Traceback" not in r.stderr
    finally:
        osmo.stop_server()


def test_a_home_open_to_others_is_made_private(tmp_path: Path) -> None:
    home = tmp_path / "home"
    home.mkdir(mode=0o755)
    os.chmod(home, 0o755)
    (home / "state.db").touch(mode=0o644)
    os.chmod(home / "state.db", 0o644)
    osmo = Osmo(home)
    try:
        r = osmo("list", check=True)
        assert "was open to other users (mode 755); made it 0700" in r.err
        assert stat.S_IMODE(home.stat().st_mode) == 0o700
        private = ["state.db", "state.db-wal", "state.db-shm", "server.json", "server.log",
                   "auth/admin.token"]
        modes = {name: stat.S_IMODE((home / name).stat().st_mode) for name in private}
        assert modes == dict.fromkeys(private, 0o600), modes
        assert stat.S_IMODE((home / "auth").stat().st_mode) == 0o700
        assert "made it 0700" not in osmo("list", check=True).err  # said once, when fixed
    finally:
        osmo.stop_server()


def test_a_home_of_another_user_is_refused(tmp_path: Path) -> None:
    home = tmp_path / "theirs"
    home.mkdir(mode=0o700)
    if os.geteuid() == 0:
        os.chown(home, NOBODY, NOBODY)
    else:
        pytest.skip("needs root to give the folder to another user")
    r = Osmo(home)("list")
    assert r.code == 3 and f"belongs to uid {NOBODY}" in r.err and "Traceback" not in r.err
    assert not (home / "server.log").exists(), "nothing was started in their home"


def test_a_wildcard_listener_without_auth_refuses_to_start(tmp_path: Path) -> None:
    osmo = Osmo(tmp_path / "home")
    wildcard = f"tcp/0.0.0.0:{free_port(0)}"
    r = osmo("server", "start", "--listen", wildcard)
    assert r.code == 2, r
    assert f"refusing to listen on {wildcard} without authentication" in r.err
    assert "in clear" in r.err and "--insecure" in r.err and "Traceback" not in r.err
    assert not lock_is_held(Home(osmo.home))
    try:
        r = osmo("server", "start", "--listen", wildcard, "--insecure")
        assert r.code == 0, r
        assert "INSECURE" in r.err and "in clear" in r.err
        assert "INSECURE: listening on" in (osmo.home / "server.log").read_text()
        assert osmo("list").code == 0
    finally:
        osmo.stop_server()


def test_a_password_protected_listener_starts_without_insecure(tmp_path: Path) -> None:
    (tmp_path / "users.txt").write_text("osmo:pw\n")
    conf = tmp_path / "server.json5"
    conf.write_text('{transport: {auth: {usrpwd: {user: "osmo", password: "pw", '
                    f'dictionary_file: "{tmp_path}/users.txt"}}}}}}}}\n')
    osmo = Osmo(tmp_path / "home")
    try:
        r = osmo("server", "start", "--listen", f"tcp/0.0.0.0:{free_port(0)}",
                 "--zenoh-config", str(conf))
        assert r.code == 0 and "INSECURE" not in r.err, r
    finally:
        osmo.stop_server()


def test_a_home_too_deep_for_a_socket_path_gets_a_private_short_one(tmp_path: Path) -> None:
    home = tmp_path / ("deep-" * 20) / "home"
    osmo = Osmo(home)
    try:
        osmo("list", check=True)
        endpoint = json.loads((osmo.home / "server.json").read_text())["endpoint"]
        sock = Path(endpoint.removeprefix("unixsock-stream/"))
        assert sock.parent == Path(f"/tmp/osmo-{os.geteuid()}") and sock.is_socket()
        assert stat.S_IMODE(sock.parent.stat().st_mode) == 0o700
        assert len(str(sock)) < 100
    finally:
        osmo.stop_server()
