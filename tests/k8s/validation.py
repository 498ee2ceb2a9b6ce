"""What the stand-in refuses on create, with the real API server's field paths and wording.

Two layers, both collecting every problem (the server answers one 422 Invalid listing them):

- :func:`check` — always on: object names (DNS-1123 subdomain; a Service a DNS-1035
  label), label and annotation keys and values, and for pods the containers (present, names
  unique DNS-1123 labels, an image each), volume mounts naming a declared volume,
  environment variable names and the restart policy; for Secrets the data keys and size.
- :class:`SchemaCheck` — optional (``ApiServer(validate="1.33")``): the object against the
  Kubernetes OpenAPI schema of that version from ``kubernetes-validate``, strict (an
  unknown field is an error). Kinds without a schema there (the PodGroup custom resources)
  pass unchecked.

A problem is a :class:`Cause`; the server turns them into a Status body.
"""

from __future__ import annotations

import base64
import binascii
import functools
import json
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import jsonschema
import kubernetes_validate.utils as kv
import referencing

__all__ = ["Cause", "SchemaCheck", "check", "decode_secret_data"]

_LABEL = r"[a-z0-9]([-a-z0-9]*[a-z0-9])?"
DNS1123_LABEL = re.compile(_LABEL)
DNS1123_SUBDOMAIN = re.compile(rf"{_LABEL}(\.{_LABEL})*")
DNS1035_LABEL = re.compile(r"[a-z]([-a-z0-9]*[a-z0-9])?")
QUALIFIED_NAME = re.compile(r"([A-Za-z0-9][-A-Za-z0-9_.]*)?[A-Za-z0-9]")
ENV_NAME = re.compile(r"[-._a-zA-Z][-._a-zA-Z0-9]*")
SECRET_KEY = re.compile(r"[-._a-zA-Z0-9]+")
SECRET_MAX = 1024 * 1024
ANNOTATIONS_MAX = 256 * 1024


@dataclass(frozen=True)
class Cause:
    """One problem: its field path, the reason code and the message, as the server words them."""

    field: str
    reason: str
    message: str

    def __str__(self) -> str:
        return f"{self.field}: {self.message}"


def check(kind: str, obj: Mapping[str, Any]) -> list[Cause]:
    """Every problem the stand-in always refuses in ``obj`` (a ``kind``), in field order."""
    meta = obj.get("metadata") or {}
    causes = list(_name(kind, meta))
    causes += _labels(meta.get("labels"), "metadata.labels")
    causes += _annotations(meta.get("annotations"))
    if kind == "Pod":
        causes += _pod(obj.get("spec") or {})
    elif kind == "Secret":
        causes += _secret(obj)
    return causes


def _name(kind: str, meta: Mapping[str, Any]) -> Iterator[Cause]:
    name = meta.get("name")
    if not name:
        yield Cause("metadata.name", "FieldValueRequired",
                    "Required value: name or generateName is required")
        return
    pattern, limit, what = ((DNS1035_LABEL, 63, "a DNS-1035 label") if kind == "Service"
                            else (DNS1123_SUBDOMAIN, 253, "a lowercase RFC 1123 subdomain"))
    if len(name) > limit or not pattern.fullmatch(name):
        yield Cause("metadata.name", "FieldValueInvalid",
                    f"Invalid value: {json.dumps(name)}: a {kind} name must be {what} "
                    f"of at most {limit} characters")


def _key(key: str, field: str) -> Iterator[Cause]:
    prefix, _, name = key.rpartition("/")
    if (len(name) > 63 or not QUALIFIED_NAME.fullmatch(name)
            or ("/" in key and (not prefix or len(prefix) > 253
                                or not DNS1123_SUBDOMAIN.fullmatch(prefix)))):
        yield Cause(field, "FieldValueInvalid",
                    f"Invalid value: {json.dumps(key)}: name part must consist of alphanumeric "
                    "characters, '-', '_' or '.', and must start and end with an alphanumeric "
                    "character (max 63), with an optional DNS subdomain prefix and '/'")


def _labels(labels: Any, field: str) -> Iterator[Cause]:
    for key, value in (labels or {}).items():
        yield from _key(key, field)
        if not isinstance(value, str) or len(value) > 63 or (
                value and not QUALIFIED_NAME.fullmatch(value)):
            yield Cause(field, "FieldValueInvalid",
                        f"Invalid value: {json.dumps(value)}: a valid label must be an empty "
                        "string or consist of alphanumeric characters, '-', '_' or '.', and "
                        "must start and end with an alphanumeric character (max 63)")


def _annotations(annotations: Any) -> Iterator[Cause]:
    total = 0
    for key, value in (annotations or {}).items():
        yield from _key(key, "metadata.annotations")
        total += len(key) + len(str(value))
    if total > ANNOTATIONS_MAX:
        yield Cause("metadata.annotations", "FieldValueTooLong",
                    f"Too long: must have at most {ANNOTATIONS_MAX} bytes")


def _pod(spec: Mapping[str, Any]) -> Iterator[Cause]:
    volumes = {v.get("name") for v in spec.get("volumes") or []}
    if not spec.get("containers"):
        yield Cause("spec.containers", "FieldValueRequired", "Required value")
    seen: set[str] = set()
    for group in ("initContainers", "containers"):
        for i, container in enumerate(spec.get(group) or []):
            yield from _container(container, f"spec.{group}[{i}]", volumes, seen)
    policy = spec.get("restartPolicy", "Always")
    if policy not in ("Always", "OnFailure", "Never"):
        yield Cause("spec.restartPolicy", "FieldValueNotSupported",
                    f'Unsupported value: {json.dumps(policy)}: supported values: "Always", '
                    '"OnFailure", "Never"')


def _container(container: Mapping[str, Any], field: str, volumes: set[Any],
               seen: set[str]) -> Iterator[Cause]:
    name = container.get("name") or ""
    if not name:
        yield Cause(f"{field}.name", "FieldValueRequired", "Required value")
    elif len(name) > 63 or not DNS1123_LABEL.fullmatch(name):
        yield Cause(f"{field}.name", "FieldValueInvalid",
                    f"Invalid value: {json.dumps(name)}: a lowercase RFC 1123 label")
    elif name in seen:
        yield Cause(f"{field}.name", "FieldValueDuplicate", f"Duplicate value: {json.dumps(name)}")
    seen.add(name)
    if not container.get("image"):
        yield Cause(f"{field}.image", "FieldValueRequired", "Required value")
    for j, mount in enumerate(container.get("volumeMounts") or []):
        if mount.get("name") not in volumes:
            yield Cause(f"{field}.volumeMounts[{j}].name", "FieldValueNotFound",
                        f"Not found: {json.dumps(mount.get('name'))}")
    for j, env in enumerate(container.get("env") or []):
        if not ENV_NAME.fullmatch(env.get("name") or ""):
            yield Cause(f"{field}.env[{j}].name", "FieldValueInvalid",
                        f"Invalid value: {json.dumps(env.get('name'))}: a valid environment "
                        "variable name must consist of alphabetic characters, digits, '_', "
                        "'-', or '.', and must not start with a digit")


def _secret(obj: Mapping[str, Any]) -> Iterator[Cause]:
    total = 0
    for group in ("data", "stringData"):
        for key, value in (obj.get(group) or {}).items():
            if not SECRET_KEY.fullmatch(key):
                yield Cause(f"{group}[{key}]", "FieldValueInvalid",
                            f"Invalid value: {json.dumps(key)}: a valid config key must "
                            "consist of alphanumeric characters, '-', '_' or '.'")
            total += len(value or "")
    if total > SECRET_MAX * 4 // 3:
        yield Cause("data", "FieldValueTooLong", f"Too long: must have at most {SECRET_MAX} bytes")


def decode_secret_data(data: Mapping[str, Any]) -> dict[str, bytes]:
    """A Secret's ``data`` decoded; raises ValueError as the server's JSON decoding does."""
    out = {}
    for key, value in data.items():
        try:
            out[key] = base64.b64decode(value or "", validate=True)
        except (binascii.Error, TypeError) as exc:
            raise ValueError(f"illegal base64 data in data[{key}]: {exc}") from None
    return out


class SchemaCheck:
    """Objects against the strict OpenAPI schema of one Kubernetes version.

    Args:
        version: a Kubernetes version ``kubernetes-validate`` ships (``"1.33"``, ``"1.37.0"``).
    """

    def __init__(self, version: str) -> None:
        wanted = kv.major_minor(version)
        known = [v for v in kv.all_versions() if kv.major_minor(v) == wanted]
        if not known:
            raise ValueError(f"kubernetes-validate has no schema for {version} "
                             f"(it has {kv.all_versions()[0]} to {kv.latest_version()})")
        self.version = known[-1]

    def __call__(self, obj: Mapping[str, Any]) -> list[Cause]:
        """Every schema error in ``obj`` (none for a kind the package has no schema for)."""
        validator = self._validator(str(obj.get("apiVersion")), str(obj.get("kind")))
        if validator is None:
            return []
        return [Cause(_path(error), "FieldValueInvalid", error.message)
                for error in sorted(validator.iter_errors(dict(obj)), key=_path)]

    @functools.lru_cache(maxsize=32)  # noqa: B019 - a handful of kinds per test session
    def _validator(self, api_version: str, kind: str) -> jsonschema.Validator | None:
        group = re.sub(r"^([^./]*)(?:\.[^/]*)?/", r"\1-", api_version)
        folder = f"kubernetes-json-schema/v{self.version}-local-strict"
        try:
            schema = kv.schema_contents(f"{folder}/{kind.lower()}-{group}.json", self.version)
        except FileNotFoundError:
            return None
        definitions = kv.schema_contents(f"{folder}/_definitions.json", self.version)
        registry = (referencing.Resource.from_contents(schema)
                    @ (referencing.Resource.from_contents(definitions) @ referencing.Registry()))
        return jsonschema.Draft202012Validator(schema, registry=registry)


def _path(error: jsonschema.ValidationError) -> str:
    out = ""
    for part in error.absolute_path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "<root>"
