"""Finding a viewer plugin: by entry point, with a clear error when it is absent or broken.

The plugins here are real distributions on ``sys.path`` (a ``*.dist-info`` folder with an
``entry_points.txt``), found by ``importlib.metadata`` as an installed one would be.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from osmo.errors import UsageError
from osmo.tasktypes.viewers import find_viewer, viewer_names


def _install(site: Path, dist: str, entries: str, module: str = "", source: str = "") -> None:
    info = site / f"{dist}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[osmo.viewers]\n{entries}\n")
    if module:
        (site / f"{module}.py").write_text(source)


@pytest.fixture()
def site(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def test_a_plugin_viewer_is_found_by_name(site: Path) -> None:
    _install(site, "toyview", "toy = toyview_mod:VIEWER", "toyview_mod", """
from pathlib import Path
class Toy:
    name, suffix = "toy", ".toy"
    def convert(self, source, out):
        Path(out).write_bytes(Path(source).read_bytes()[::-1])
        return Path(out)
    def open(self, path):
        return False
VIEWER = Toy()
""")
    assert "toy" in viewer_names()
    viewer = find_viewer("toy")
    src, out = site / "a.mcap", site / "a.toy"
    src.write_bytes(b"abc")
    assert viewer.convert(src, out) == out and out.read_bytes() == b"cba"


def test_an_unknown_viewer_names_the_installed_ones(site: Path) -> None:
    with pytest.raises(UsageError, match=r"no viewer 'nope'; installed: .*rerun"):
        find_viewer("nope")


def test_a_viewer_missing_its_dependency_names_the_extra(site: Path) -> None:
    _install(site, "needy", "needy = needy_mod:VIEWER [viz]", "needy_mod",
             "import osmo_no_such_dependency\n")
    with pytest.raises(UsageError, match=r'needs module .osmo_no_such_dependency.*'
                                         r'pip install "osmo\[viz\]"'):
        find_viewer("needy")


def test_an_object_without_the_viewer_shape_is_refused(site: Path) -> None:
    _install(site, "shapeless", "shapeless = shapeless_mod:VIEWER", "shapeless_mod",
             "VIEWER = 42\n")
    with pytest.raises(UsageError, match="does not have the shape of a viewer"):
        find_viewer("shapeless")
