"""``s3://bucket/prefix`` URLs: any S3-compatible object store, with the standard library only.

Owns the S3 wire protocol osmo needs — AWS Signature Version 4 (:func:`sign`), path-style
requests (``{endpoint}/{bucket}/{key}``) over one kept-alive ``http.client`` connection,
ListObjectsV2 with continuation tokens, single-request PUT, streaming GET, DELETE — and the
translation of every HTTP and network failure into :class:`~osmo.urls.base.UrlError`. Must not
import boto3 or any other third-party library (the core install stays light), implement the
marker protocol (:class:`osmo.urls.base.Transfer` does), or let a secret reach a message, a
``repr`` or a log.

Credential keys: ``endpoint`` (default ``https://s3.amazonaws.com``; e.g.
``http://127.0.0.1:9000`` for MinIO), ``access_key`` and ``secret_key`` (both or neither;
neither sends unsigned requests, for public buckets), ``region`` (default ``us-east-1``),
``session_token`` (temporary credentials). Any other key is a :class:`UsageError`.

Limits: one object is one PUT, so a file over 5 GiB (S3's single-PUT limit) is refused before
the upload starts; multipart upload is not implemented. Each body is hashed before it is sent
(``x-amz-content-sha256`` is the payload's sha256), so S3 itself rejects a file that changes
while it is being uploaded.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import http.client
import os
import ssl
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import BinaryIO
from urllib.parse import quote, urlsplit

from osmo.errors import UsageError
from osmo.urls.base import UrlError, check_path, copy_hashing, hash_file

__all__ = ["S3Store", "sign"]

DEFAULT_ENDPOINT = "https://s3.amazonaws.com"
DEFAULT_REGION = "us-east-1"
MAX_PUT = 5 * 1024**3  # S3 refuses a single PUT above 5 GiB
EMPTY_SHA256 = hashlib.sha256(b"").hexdigest()
TIMEOUT = 60.0
KEYS = ("endpoint", "access_key", "secret_key", "region", "session_token")
_DENIED = {"AccessDenied", "InvalidAccessKeyId", "SignatureDoesNotMatch", "InvalidToken",
           "ExpiredToken", "InvalidClientTokenId"}


def parse_s3_url(url: str) -> tuple[str, str]:
    """Split ``s3://bucket/prefix`` into ``(bucket, prefix without surrounding slashes)``.

    Raises:
        UsageError: no bucket, or a query or fragment.
    """
    parts = urlsplit(url)
    if parts.scheme.lower() != "s3" or not parts.netloc or parts.query or parts.fragment:
        raise UsageError(f"S3 URL {url!r} must look like s3://bucket/prefix")
    return parts.netloc, parts.path.strip("/")


def canonical_query(query: Mapping[str, str]) -> str:
    """SigV4's canonical query string (also used verbatim as the request's query)."""
    pairs = sorted((quote(k, safe=""), quote(v, safe="")) for k, v in query.items())
    return "&".join(f"{k}={v}" for k, v in pairs)


def sign(method: str, path: str, query: Mapping[str, str], headers: Mapping[str, str],
         payload_sha256: str, *, access_key: str, secret_key: str, region: str) -> str:
    """Return the SigV4 ``Authorization`` header value for one S3 request.

    Args:
        method: the HTTP method.
        path: the request path, not yet percent-encoded (``/bucket/key``).
        query: the query parameters.
        headers: every header to sign; must hold ``host`` and ``x-amz-date``
            (``YYYYMMDDTHHMMSSZ``).
        payload_sha256: hex sha256 of the body (as sent in ``x-amz-content-sha256``).
        access_key: the key id (goes into the header in clear, as SigV4 requires).
        secret_key: the secret (only ever used as an HMAC key).
        region: the signing region.
    """
    lowered = sorted((k.lower(), " ".join(v.split())) for k, v in headers.items())
    amz_date = dict(lowered)["x-amz-date"]
    signed = ";".join(k for k, _ in lowered)
    request = "\n".join([method, quote(path, safe="/"), canonical_query(query),
                         "".join(f"{k}:{v}\n" for k, v in lowered), signed, payload_sha256])
    scope = f"{amz_date[:8]}/{region}/s3/aws4_request"
    to_sign = "\n".join(["AWS4-HMAC-SHA256", amz_date, scope,
                         hashlib.sha256(request.encode()).hexdigest()])
    key = ("AWS4" + secret_key).encode()
    for part in (amz_date[:8], region, "s3", "aws4_request"):
        key = hmac.new(key, part.encode(), hashlib.sha256).digest()
    signature = hmac.new(key, to_sign.encode(), hashlib.sha256).hexdigest()
    return (f"AWS4-HMAC-SHA256 Credential={access_key}/{scope},SignedHeaders={signed},"
            f"Signature={signature}")


class S3Store:
    """The objects under ``s3://bucket/prefix/`` as a :class:`~osmo.urls.base.ObjectStore`.

    Not thread-safe: one store holds one connection. ``repr`` shows no credential.

    Attributes:
        url: the URL as given.
        bucket: the bucket.
        prefix: the key prefix, without surrounding slashes (``""``: the whole bucket).
        endpoint: the endpoint URL.
        region: the signing region.
        max_object_size: 5 GiB, the single-PUT limit.
    """

    max_object_size: int | None = MAX_PUT

    def __init__(self, url: str, credential: Mapping[str, str] | None = None) -> None:
        """Parse ``url`` and ``credential`` (see the module docstring); no request is sent.

        Raises:
            UsageError: a malformed URL or endpoint, an unknown key, or only one of
                ``access_key``/``secret_key``.
        """
        cred = dict(credential or {})
        unknown = sorted(set(cred) - set(KEYS))
        if unknown:
            raise UsageError(f"{url}: unknown S3 credential keys {unknown}; "
                             f"accepted: {', '.join(KEYS)}")
        if ("access_key" in cred) != ("secret_key" in cred):
            raise UsageError(f"{url}: an S3 credential needs both access_key and secret_key "
                             "(or neither, for a public bucket)")
        self.url = url
        self.bucket, self.prefix = parse_s3_url(url)
        self.endpoint = cred.get("endpoint", DEFAULT_ENDPOINT).rstrip("/")
        self.region = cred.get("region", DEFAULT_REGION)
        self._access = cred.get("access_key")
        self._secret = cred.get("secret_key")
        self._token = cred.get("session_token")
        ep = urlsplit(self.endpoint)
        if ep.scheme not in ("http", "https") or not ep.hostname:
            raise UsageError(f"{url}: S3 endpoint {self.endpoint!r} must be an http(s) URL, "
                             "e.g. http://127.0.0.1:9000")
        self._https = ep.scheme == "https"
        self._host = ep.hostname
        self._port = ep.port
        self._netloc = ep.netloc.rsplit("@", 1)[-1]
        self._base = ep.path.rstrip("/")
        self._conn: http.client.HTTPConnection | None = None

    def __repr__(self) -> str:
        return f"S3Store({self.url!r}, endpoint={self.endpoint!r})"

    def make_bucket(self) -> None:
        """Create the bucket (for setup scripts and tests); an already owned bucket is fine."""
        body = b""
        if self.region != "us-east-1":
            body = (b"<CreateBucketConfiguration><LocationConstraint>" + self.region.encode()
                    + b"</LocationConstraint></CreateBucketConfiguration>")
        resp = self._send("PUT", None, {}, body)
        data = resp.read()
        self._close()
        if resp.status != 200 and _code(data) != "BucketAlreadyOwnedByYou":
            raise self._error(resp.status, data, None)

    def list(self) -> Iterator[tuple[str, int]]:
        """Yield ``(path, size)`` for every key under the prefix, one page at a time."""
        start = self.prefix + "/" if self.prefix else ""
        query = {"list-type": "2", "prefix": start}
        while True:
            resp = self._send("GET", None, query, b"")
            data = resp.read()
            if resp.status != 200:
                raise self._error(resp.status, data, None)
            try:
                root = _strip_ns(ET.fromstring(data))
            except ET.ParseError as e:
                raise UrlError(f"{self.url}: unreadable listing from {self.endpoint}: "
                               f"{e}") from None
            for item in root.iter("Contents"):
                key = item.findtext("Key", "")
                if key.startswith(start) and not key.endswith("/"):
                    yield key[len(start):], int(item.findtext("Size", "0"))
            token = root.findtext("NextContinuationToken")
            if root.findtext("IsTruncated") != "true" or not token:
                return
            query = {**query, "continuation-token": token}

    def read(self, path: str) -> bytes | None:
        """Return the object's bytes, or ``None`` if the key does not exist."""
        resp = self._send("GET", self._key(path), {}, b"")
        data = resp.read()
        if resp.status == 404 and _code(data) != "NoSuchBucket":
            return None
        if resp.status != 200:
            raise self._error(resp.status, data, path)
        return data

    def get(self, path: str, dest: Path) -> tuple[int, str]:
        """Stream the object into the new file ``dest``; return its ``(size, sha256 hex)``."""
        with open(dest, "xb") as out:
            resp = self._send("GET", self._key(path), {}, b"")
            if resp.status != 200:
                raise self._error(resp.status, resp.read(), path)
            try:
                return copy_hashing(resp.read, out)
            except (http.client.HTTPException, ConnectionError, TimeoutError) as e:
                self._close()
                raise UrlError(self._scrub(f"{self._where(path)}: download interrupted: "
                                           f"{e!r}")) from None

    def put(self, path: str, src: Path) -> tuple[int, str]:
        """Upload the file ``src`` in one PUT (hashed first); return ``(size, sha256 hex)``."""
        size, sha = hash_file(src)
        if size > MAX_PUT:
            raise UrlError(f"{self._where(path)}: {src} is {size} bytes, over S3's 5 GiB "
                           "single-PUT limit (multipart upload is not implemented)")
        self._put(path, src, sha)
        return size, sha

    def write(self, path: str, data: bytes) -> None:
        """Upload ``data`` as one object."""
        self._put(path, data, hashlib.sha256(data).hexdigest())

    def delete(self, path: str) -> None:
        """Delete the object; a missing key is not an error."""
        resp = self._send("DELETE", self._key(path), {}, b"")
        data = resp.read()
        if resp.status not in (200, 204) and not (resp.status == 404 and
                                                   _code(data) == "NoSuchKey"):
            raise self._error(resp.status, data, path)

    def close(self) -> None:
        """Close the kept-alive connection; the next request opens a new one."""
        self._close()

    def __del__(self) -> None:
        """Close the socket of a store dropped without :meth:`close`."""
        self._close()

    def _put(self, path: str, body: bytes | Path, sha: str) -> None:
        """PUT one object whose body hashes to ``sha``."""
        resp = self._send("PUT", self._key(path), {}, body, sha)
        data = resp.read()
        if resp.status != 200:
            raise self._error(resp.status, data, path)

    def _key(self, path: str) -> str:
        """The object key of a relative path (checked: no ``..``, no leading ``/``)."""
        path = check_path(path, self.url)
        return f"{self.prefix}/{path}" if self.prefix else path

    def _where(self, path: str | None) -> str:
        """The ``s3://`` URL of a relative path, for messages (the store's URL for ``None``)."""
        return f"s3://{self.bucket}/{self._key(path)}" if path is not None else self.url

    def _send(self, method: str, key: str | None, query: Mapping[str, str],
              body: bytes | Path, sha: str = EMPTY_SHA256) -> http.client.HTTPResponse:
        """Send one signed request and return its response, status unchecked.

        A request on a kept-alive connection that the server had closed is retried once on a
        new one (every request osmo sends is idempotent).
        """
        path = f"{self._base}/{self.bucket}" + (f"/{key}" if key is not None else "")
        target = quote(path, safe="/") + (f"?{canonical_query(query)}" if query else "")
        with contextlib.ExitStack() as stack:
            src = stack.enter_context(open(body, "rb")) if isinstance(body, Path) else None
            for attempt in (1, 2):
                fresh = self._conn is None
                conn = self._connect()
                headers = self._headers(method, path, query, sha)
                data = body if isinstance(body, bytes) else b""
                headers["Content-Length"] = str(len(data))
                payload: bytes | BinaryIO = data
                if src is not None:
                    src.seek(0)
                    payload = src
                    headers["Content-Length"] = str(os.fstat(src.fileno()).st_size)
                try:
                    conn.request(method, target, body=payload, headers=headers)
                    return conn.getresponse()
                except (http.client.HTTPException, OSError) as e:
                    self._close()
                    if fresh or attempt == 2:
                        raise UrlError(self._scrub(
                            f"{self._where_key(key)}: cannot reach S3 endpoint "
                            f"{self.endpoint}: {e!r}")) from None
        raise AssertionError("unreachable: the second attempt returns or raises")

    def _where_key(self, key: str | None) -> str:
        """The ``s3://`` URL of a full key, for messages."""
        return f"s3://{self.bucket}/{key}" if key is not None else self.url

    def _headers(self, method: str, path: str, query: Mapping[str, str],
                 sha: str) -> dict[str, str]:
        """The request's headers, signed when the store has keys."""
        headers = {"host": self._netloc, "x-amz-content-sha256": sha,
                   "x-amz-date": datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")}
        if self._token:
            headers["x-amz-security-token"] = self._token
        if self._access and self._secret:
            headers["Authorization"] = sign(method, path, query, headers, sha,
                                            access_key=self._access, secret_key=self._secret,
                                            region=self.region)
        return headers

    def _connect(self) -> http.client.HTTPConnection:
        """The kept-alive connection, opened if there is none."""
        if self._conn is None:
            if self._https:
                self._conn = http.client.HTTPSConnection(
                    self._host, self._port, timeout=TIMEOUT,
                    context=ssl.create_default_context())
            else:
                self._conn = http.client.HTTPConnection(self._host, self._port, timeout=TIMEOUT)
        return self._conn

    def _close(self) -> None:
        """Drop the connection (after an error its state is unknown)."""
        conn: http.client.HTTPConnection | None = getattr(self, "_conn", None)  # __init__ may fail
        if conn is not None:
            conn.close()
            self._conn = None

    def _error(self, status: int, body: bytes, path: str | None) -> UrlError:
        """Translate an S3 error answer into a :class:`UrlError` that names the URL."""
        code = _code(body)
        where = self._where(path)
        if status == 403 or code in _DENIED:
            msg = (f"{where}: access denied: check the credential's keys (access_key, "
                   f"secret_key, session_token) and the bucket's permissions [{code or 403}]")
        elif code == "NoSuchBucket":
            msg = f"{where}: bucket not found: {self.bucket!r} does not exist at {self.endpoint}"
        elif status == 404:
            msg = f"{where}: object not found"
        else:
            detail = _text(body, "Message")
            msg = f"{where}: S3 answered HTTP {status} {code}: {detail}".rstrip(": ")
            if status == 301 or code in ("PermanentRedirect", "AuthorizationHeaderMalformed"):
                msg += "; the bucket is in another region: set the credential's region and endpoint"
        return UrlError(self._scrub(msg))

    def _scrub(self, text: str) -> str:
        """Mask the secret and token should a server or library ever echo them."""
        for secret in (self._secret, self._token):
            if secret:
                text = text.replace(secret, "***")
        return text


def _strip_ns(root: ET.Element) -> ET.Element:
    """Drop XML namespaces in place so lookups work whatever namespace a server uses."""
    for el in root.iter():
        if isinstance(el.tag, str) and "}" in el.tag:
            el.tag = el.tag.split("}", 1)[1]
    return root


def _text(body: bytes, field: str) -> str:
    """The text of ``field`` in an S3 XML error body, or ``""``."""
    try:
        return _strip_ns(ET.fromstring(body)).findtext(field, "") if body else ""
    except ET.ParseError:
        return ""


def _code(body: bytes) -> str:
    """The ``Code`` of an S3 XML error body, or ``""``."""
    return _text(body, "Code")
