"""file:// specifics, scheme dispatch and the package's public surface."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

import osmo.urls
from osmo.errors import InfrastructureError, UsageError
from osmo.urls import UrlError, for_url
from osmo.urls.base import Transfer
from osmo.urls.local import FileStore


def test_public_surface() -> None:
    assert sorted(osmo.urls.__all__) == ["MARKER", "Remote", "UrlError", "for_url"]
    assert issubclass(UrlError, InfrastructureError) and UrlError.exit_code == 3


def test_unknown_scheme_lists_the_supported_ones() -> None:
    with pytest.raises(UsageError, match="supported schemes are file://, s3://"):
        for_url("gs://bucket/x")
    with pytest.raises(UsageError, match="unsupported URL"):
        for_url("/just/a/path")


@pytest.mark.parametrize(("url", "match"), [
    ("file://host/data", "names host 'host'"),
    ("file://relative/x", "names host 'relative'"),
    ("file:relative/x", "must be an absolute path"),
    ("file:///data?x=1", "must be an absolute path"),
])
def test_file_url_must_be_absolute_and_local(url: str, match: str) -> None:
    with pytest.raises(UsageError, match=match):
        for_url(url)


def test_file_url_takes_no_credential() -> None:
    with pytest.raises(UsageError, match="take no credential"):
        for_url("file:///tmp/x", {"access_key": "a"})


def test_file_url_is_percent_decoded(tmp_path: Path) -> None:
    r = for_url(f"file://{tmp_path}/with%20space/")
    assert isinstance(r, Transfer) and isinstance(r.store, FileStore)
    assert r.store.root == tmp_path / "with space"


def test_upload_leaves_no_temporary_files(tmp_path: Path) -> None:
    (tmp_path / "src" / "d").mkdir(parents=True)
    (tmp_path / "src" / "d" / "f").write_bytes(b"x")
    for_url(f"file://{tmp_path}/remote").upload(tmp_path / "src")
    assert sorted(p.name for p in (tmp_path / "remote").rglob("*")) == [
        ".osmo-complete.json", "d", "f"]


def test_upload_onto_a_file_is_a_url_error(tmp_path: Path) -> None:
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "f").write_bytes(b"x")
    (tmp_path / "taken").write_bytes(b"a file, not a folder")
    with pytest.raises(UrlError, match="uploading to file://"):
        for_url(f"file://{tmp_path}/taken").upload(tmp_path / "src")


def test_download_refuses_a_folder_in_a_files_way(tmp_path: Path) -> None:
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "f").write_bytes(b"x")
    r = for_url(f"file://{tmp_path}/remote")
    r.upload(tmp_path / "src")
    (tmp_path / "dest" / "f").mkdir(parents=True)
    with pytest.raises(UrlError, match="f is a folder there"):
        r.download(tmp_path / "dest")


def test_schemes_import_lazily() -> None:
    code = ("import sys, osmo.urls; "
            "assert 'osmo.urls.s3' not in sys.modules and 'http.client' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)
