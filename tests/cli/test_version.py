"""``osmo --version``: the version the installed package's metadata gives, exit 0."""

from __future__ import annotations

from importlib.metadata import version
from pathlib import Path

from tests.conftest import Osmo


def test_version_prints_the_package_metadata_version(tmp_path: Path) -> None:
    osmo = Osmo(tmp_path / "home")
    r = osmo("--version")
    assert (r.code, r.out, r.err) == (0, f"osmo {version('osmo')}\n", "")
    assert not (tmp_path / "home" / "server.json").exists()  # no server for this
