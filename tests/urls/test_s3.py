"""s3:// specifics: SigV4 against AWS's published examples, and a real s3rver on loopback."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from osmo.errors import UsageError
from osmo.urls import UrlError, for_url
from osmo.urls.base import Transfer
from osmo.urls.s3 import EMPTY_SHA256, S3Store, sign
from tests.urls import s3server

# From AWS's "Signature Calculations for the Authorization Header" examples for S3.
AWS_KEYS = {"access_key": "AKIAIOSFODNN7EXAMPLE",
            "secret_key": "wJalrXUtnFEMI/K7MDENG/bPxRfiCYEXAMPLEKEY", "region": "us-east-1"}
AWS_HEADERS = {"host": "examplebucket.s3.amazonaws.com", "x-amz-date": "20130524T000000Z",
               "x-amz-content-sha256": EMPTY_SHA256}
PUT_SHA = "44ce7dd67c959e0d3524ffac1771dfbba87d2b6b4b4e99e42034a8b803f8b072"
AWS_EXAMPLES = [
    ("GET", "/test.txt", {}, {"range": "bytes=0-9"}, EMPTY_SHA256,
     "f0e8bdb87c964420e857bd35b5d6ed310bd44f0170aba48dd91039c6036bdb41"),
    ("PUT", "/test$file.text", {}, {"date": "Fri, 24 May 2013 00:00:00 GMT",
                                    "x-amz-storage-class": "REDUCED_REDUNDANCY",
                                    "x-amz-content-sha256": PUT_SHA}, PUT_SHA,
     "98ad721746da40c64f1a55b78f14c238d841ea1380cd77a1b5971af0ece108bd"),
    ("GET", "/", {"lifecycle": ""}, {}, EMPTY_SHA256,
     "fea454ca298b7da1c68078a5d1bdbfbbe0d65c699e0f91ac7a200a0136783543"),
    ("GET", "/", {"max-keys": "2", "prefix": "J"}, {}, EMPTY_SHA256,
     "34b48302e7b5fa45bde8084f4b7868a86f0a534bc59db6670ed5711ef69dc6f7"),
]


@pytest.mark.parametrize(("method", "path", "query", "extra", "sha", "signature"), AWS_EXAMPLES)
def test_sigv4_matches_aws_examples(method: str, path: str, query: dict[str, str],
                                    extra: dict[str, str], sha: str, signature: str) -> None:
    auth = sign(method, path, query, {**AWS_HEADERS, **extra}, sha, **AWS_KEYS)
    assert auth.startswith("AWS4-HMAC-SHA256 Credential=AKIAIOSFODNN7EXAMPLE/20130524/"
                           "us-east-1/s3/aws4_request,SignedHeaders=")
    assert auth.endswith(f",Signature={signature}")


@pytest.mark.parametrize(("url", "cred", "match"), [
    ("s3:///no-bucket", None, "s3://bucket/prefix"),
    ("s3://b/p?versionId=1", None, "s3://bucket/prefix"),
    ("s3://b/p", {"secret": "x"}, "unknown S3 credential keys \\['secret'\\]"),
    ("s3://b/p", {"access_key": "a"}, "both access_key and secret_key"),
    ("s3://b/p", {"endpoint": "ftp://host"}, "must be an http\\(s\\) URL"),
])
def test_bad_url_or_credential_is_a_usage_error(url: str, cred: dict[str, str] | None,
                                                match: str) -> None:
    with pytest.raises(UsageError, match=match):
        for_url(url, cred)


def test_repr_hides_the_secret() -> None:
    r = for_url("s3://b/p", {"access_key": "AK", "secret_key": "very-secret-value"})
    assert isinstance(r, Transfer)
    assert "very-secret-value" not in repr(r) + repr(r.store) + str(vars(r))


def test_wrong_key_is_access_denied_without_the_secret(s3_bucket: str, s3_endpoint: str,
                                                       tmp_path: Path) -> None:
    secret = "sup3r-s3cret-value-do-not-print"
    cred = {"endpoint": s3_endpoint, "access_key": "NOT-A-KEY", "secret_key": secret}
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "a").write_bytes(b"1")
    r = for_url(f"s3://{s3_bucket}/denied", cred)
    calls: list[Callable[[], list[str]]] = [lambda: r.upload(tmp_path / "src"),
                                            lambda: r.download(tmp_path / "dest")]
    for call in calls:
        with pytest.raises(UrlError, match="access denied: check the credential's keys") as e:
            call()
        text = str(e.value) + repr(e.value) + repr(e.value.__cause__) + repr(e.value.__context__)
        assert secret not in text
        assert f"s3://{s3_bucket}/denied" in str(e.value)
        assert e.value.exit_code == 3


def test_missing_bucket_is_named(s3_credential: dict[str, str], tmp_path: Path) -> None:
    with pytest.raises(UrlError, match="bucket not found: 'no-such-bucket'"):
        for_url("s3://no-such-bucket/x", s3_credential).download(tmp_path / "d")


def test_unreachable_endpoint(tmp_path: Path) -> None:
    cred = {"endpoint": f"http://127.0.0.1:{s3server.free_port()}", "access_key": "a",
            "secret_key": "unreachable-secret"}
    with pytest.raises(UrlError, match="cannot reach S3 endpoint") as e:
        for_url("s3://b/x", cred).download(tmp_path / "d")
    assert "unreachable-secret" not in str(e.value)


def test_listing_pages_past_1000_objects(s3_bucket: str, s3_credential: dict[str, str],
                                         tmp_path: Path) -> None:
    src = tmp_path / "src"
    for i in range(1005):
        (src / f"d{i % 3}").mkdir(parents=True, exist_ok=True)
        (src / f"d{i % 3}" / f"f{i:04d}").write_bytes(str(i).encode())
    r = for_url(f"s3://{s3_bucket}/many", s3_credential)
    assert isinstance(r, Transfer)
    assert len(r.upload(src)) == 1005
    assert len(list(r.store.list())) == 1006  # two pages: the files and the marker
    r.store.delete(".osmo-complete.json")  # now the download must list, across pages
    got = r.download(tmp_path / "dest")
    assert len(got) == 1005
    assert (tmp_path / "dest" / "d2" / "f1004").read_bytes() == b"1004"


def test_prefixes_do_not_leak_into_each_other(s3_bucket: str, s3_credential: dict[str, str],
                                              tmp_path: Path) -> None:
    data = S3Store(f"s3://{s3_bucket}/data", s3_credential)
    data2 = S3Store(f"s3://{s3_bucket}/data2", s3_credential)
    data.write("a", b"1")
    data2.write("b", b"2")
    data.close()
    data2.close()
    assert for_url(f"s3://{s3_bucket}/data/", s3_credential).download(tmp_path / "d") == ["a"]


def test_whole_bucket_as_prefix(s3_credential: dict[str, str], tmp_path: Path) -> None:
    bucket = "osmo-test-whole"
    S3Store(f"s3://{bucket}", s3_credential).make_bucket()
    (tmp_path / "src" / "x").mkdir(parents=True)
    (tmp_path / "src" / "x" / "y").write_bytes(b"z")
    r = for_url(f"s3://{bucket}", s3_credential)
    assert r.upload(tmp_path / "src") == ["x/y"]
    assert r.download(tmp_path / "dest") == ["x/y"]
