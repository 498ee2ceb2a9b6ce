"""Fixtures for the URL adapters: a real s3rver on loopback, and one factory per scheme.

``remote`` is parametrized over every scheme, so the contract tests in ``test_contract.py``
run unchanged against ``file://`` and ``s3://``.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from osmo.urls import for_url
from osmo.urls.base import Transfer
from osmo.urls.s3 import S3Store
from tests.urls import s3server

_buckets = itertools.count(1)


@pytest.fixture(scope="session")
def s3_endpoint(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """The endpoint of one s3rver for the session; skips only if s3rver cannot be installed."""
    try:
        s3server.install()
    except s3server.Unavailable as e:
        pytest.skip(f"no S3 test server: {e}")
    with s3server.s3rver(tmp_path_factory.mktemp("s3rver") / "data") as endpoint:
        yield endpoint


@pytest.fixture
def s3_credential(s3_endpoint: str) -> dict[str, str]:
    """A working credential for the session's s3rver."""
    return {"endpoint": s3_endpoint, "access_key": s3server.ACCESS_KEY,
            "secret_key": s3server.SECRET_KEY}


@pytest.fixture
def s3_bucket(s3_credential: dict[str, str]) -> str:
    """A new, empty bucket on the session's s3rver."""
    name = f"osmo-test-{next(_buckets)}"
    S3Store(f"s3://{name}", s3_credential).make_bucket()
    return name


Make = Callable[[str], Transfer]


@pytest.fixture(params=["file", "s3"])
def remote(request: pytest.FixtureRequest, tmp_path: Path) -> Make:
    """A factory: ``remote(prefix)`` is the :class:`Transfer` for that prefix on the scheme."""
    if request.param == "file":
        return lambda prefix: _transfer(for_url(f"file://{tmp_path}/remote/{prefix}"))
    bucket = request.getfixturevalue("s3_bucket")
    cred = request.getfixturevalue("s3_credential")
    return lambda prefix: _transfer(for_url(f"s3://{bucket}/{prefix}", cred))


def _transfer(r: object) -> Transfer:
    assert isinstance(r, Transfer)
    return r

