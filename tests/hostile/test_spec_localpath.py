"""``files: localpath:`` stays inside the spec's folder tree, and never reads osmo's home.

Issue 26 item 7: ``localpath`` read any path the submitter could read, ``../..`` included, and
osmo's own ``auth/admin.token``; the file's contents are inlined into the stored spec, which
every user may print with ``osmo spec``. Now a path that resolves (symlinks followed) outside
the spec's folder is a spec error at its ``FILE:LINE:COL`` naming the path and the rule;
``--allow-localpath DIR`` widens the tree, but never to osmo's home.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from osmo.errors import SpecError
from osmo.spec import load_spec
from tests.conftest import Osmo, write

HEAD = "workflow:\n  name: lp\n  tasks:\n  - name: t\n    command: [cat, /x/f]\n    files:\n"


def _spec(folder: Path, *localpaths: str) -> Path:
    """A spec in ``folder`` whose task gets one file per ``localpaths`` entry (line 8, 10...)."""
    body = "".join(f"    - path: /x/f{i}\n      localpath: {p}\n"
                   for i, p in enumerate(localpaths))
    return write(folder / "wf.yaml", HEAD + body)


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    """``tmp/proj`` (the spec's folder, with ``ok.txt``) beside ``tmp/secret.txt``."""
    write(tmp_path / "secret.txt", "TOP-SECRET outside the tree\n")
    write(tmp_path / "proj" / "data" / "ok.txt", "fine\n")
    return tmp_path / "proj"


@pytest.mark.parametrize("target", ["../secret.txt", "data/../../secret.txt", "ABS", "LINK",
                                    "/etc/hostname"])
def test_a_localpath_outside_the_spec_folder_is_a_spec_error(osmo: Osmo, tree: Path,
                                                             target: str) -> None:
    if target == "ABS":
        target = str(tree.parent / "secret.txt")
    if target == "LINK":  # a symlink inside the tree that leaves it
        os.symlink(tree.parent / "secret.txt", tree / "data" / "link.txt")
        target = "data/link.txt"
    spec = _spec(tree, target)
    for argv in (("validate", str(spec)), ("submit", str(spec)),
                 ("submit", "--dry-run", str(spec))):
        r = osmo(*argv)
        assert r.code == 2, (argv, r)
        assert f"{spec}:8:18: localpath '{target}' in task 't' resolves to " in r.err, r.err
        assert f"outside the spec's folder {tree}" in r.err and "--allow-localpath" in r.err
        assert "TOP-SECRET" not in r.out + r.err and "Traceback" not in r.err
    assert "lp-" not in osmo("list", check=True).out


def test_every_bad_localpath_is_listed_at_once(tree: Path) -> None:
    spec = _spec(tree, "../secret.txt", "data/ok.txt", "/etc/hostname")
    with pytest.raises(SpecError) as info:
        load_spec(spec)
    lines = str(info.value).splitlines()
    assert [ln.split(": ")[0] for ln in lines] == [f"{spec}:8:18", f"{spec}:12:18"], lines


def test_allow_localpath_widens_the_tree(osmo: Osmo, tree: Path) -> None:
    spec = _spec(tree, "../secret.txt", "data/ok.txt")
    wf = osmo.submit(spec, "--allow-localpath", str(tree.parent))
    assert "TOP-SECRET outside the tree" in osmo("spec", wf, check=True).out
    r = osmo("validate", str(spec), "--allow-localpath", str(tree.parent / "elsewhere"),
             "--allow-localpath", str(tree.parent))
    assert r.code == 0, r


def test_osmos_home_is_never_read(osmo: Osmo, tree: Path) -> None:
    osmo("list", check=True)  # the server has made its admin token
    token = osmo.home / "auth" / "admin.token"
    assert token.is_file()
    os.symlink(osmo.home, tree / "home-link")
    for target in (str(token), "home-link/auth/admin.token", "home-link/state.db"):
        spec = _spec(tree, target)
        for allow in (str(tree.parent), "/"):
            r = osmo("submit", str(spec), "--allow-localpath", allow)
            assert r.code == 2, r
            assert f"{spec}:8:18: localpath '{target}' in task 't' resolves to " in r.err
            assert f"inside osmo's home {osmo.home}, which a spec may never read" in r.err
            assert token.read_text().strip() not in r.out + r.err
    assert "lp-" not in osmo("list", check=True).out


def test_a_stored_spec_reads_no_local_file(tree: Path) -> None:
    """A spec given as data (what a server or worker receives) never reads a local file."""
    from osmo.spec import spec_from_dict

    data = {"workflow": {"name": "x", "tasks": [{"name": "t", "command": ["true"], "files": [
        {"path": "/x/f", "localpath": str(tree / "data" / "ok.txt")}]}]}}
    with pytest.raises(SpecError, match="only a spec file's own folder"):
        spec_from_dict(data)
