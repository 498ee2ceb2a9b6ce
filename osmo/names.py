"""User-chosen names: one pattern, one length limit and one message for every name a user picks.

Workflow, group and task names, dataset names and dataset tags all match :data:`NAME_RE`:
letters, digits, ``-`` and ``_``, starting with a letter and ending with a letter or a digit,
at most :data:`MAX_NAME` characters. Such a name is safe as one path component, a zenoh key
chunk and a log label, so whatever takes a name from a user (a spec, the CLI, the SDK, the
server API) checks it here before the name touches a path. Workflow ids are ``NAME-N``.
Container image references follow the OCI reference grammar (:func:`image_problem`).
Dataset references are ``NAME[:TAG|VERSION|latest]``; ``latest`` and numbers name versions,
so they cannot be tags (a tag starts with a letter, and ``latest`` is reserved). A worker's
name is looser, so that its default (``HOSTNAME-PID``) passes: letters, digits, ``.``, ``-``
and ``_``, starting and ending with a letter or digit (:func:`check_worker_name`).

Pure functions; the bottom layer (imports only ``osmo.errors``).
"""

from __future__ import annotations

import difflib
import inspect
import re
import sys
from collections.abc import Iterable
from typing import Any

from osmo.errors import UsageError

__all__ = ["MAX_NAME", "NAME_RE", "check_label", "check_name", "check_tag", "check_worker_name",
           "check_workflow_id", "did_you_mean", "image_problem", "name_problem", "object_ref",
           "parse_ref", "ref_problem", "shown", "workflow_id_problem"]

NAME_RE = re.compile(r"[a-zA-Z](?:[a-zA-Z0-9_-]*[a-zA-Z0-9])?")
MAX_NAME = 64
_MAX_ID = MAX_NAME + 21  # NAME-N, N a 64-bit counter at most
_WORKER_RE = re.compile(r"[a-zA-Z0-9](?:[a-zA-Z0-9._-]*[a-zA-Z0-9])?")
_MAX_WORKER = 253 + 21  # a host name, '-', a process id
_LATEST = "latest"
_VERSION = re.compile(r"[0-9]{1,18}")


def _rule(limit: int) -> str:
    return ("use letters, digits, '-' and '_', starting with a letter and ending with a letter "
            f"or digit, at most {limit} characters")

_SHOWN = 40  # characters of a bad value echoed in a message


def shown(value: object) -> str:
    """``value`` quoted for a message: control characters escaped, long values cut."""
    text = str(value)
    if len(text) <= _SHOWN:
        return repr(text)
    quoted = repr(text[:_SHOWN])
    return f"{quoted[:-1]}...{quoted[-1]} ({len(text)} characters)"


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the closest of ``choices`` to ``word``, or an empty string."""
    close = difflib.get_close_matches(word, list(choices), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _suggestion(name: str, limit: int) -> str:
    """`` (did you mean 'x'?)`` with a valid name made from ``name``, or an empty string."""
    guess = re.sub(r"[^a-zA-Z0-9_-]+", "-", name[:1000])
    guess = re.sub(r"^[^a-zA-Z]+", "", guess)[:limit].rstrip("-_")
    return f" (did you mean '{guess}'?)" if guess and NAME_RE.fullmatch(guess) else ""


def name_problem(name: object, what: str, *, limit: int = MAX_NAME) -> str | None:
    """Why ``name`` cannot be a ``what`` (e.g. "dataset name"), or None if it can."""
    if not isinstance(name, str):
        return f"{what} must be a string, not {type(name).__name__}"
    if not name:
        return f"{what} must not be empty; {_rule(limit)}"
    if len(name) <= limit and NAME_RE.fullmatch(name):
        return None
    if len(name) > limit:
        return (f"{what} {shown(name)} is too long: the limit is {limit} characters"
                f"{_suggestion(name, limit)}")
    return (f"{what} {shown(name)} is not a valid name: {_rule(limit)}"
            f"{_suggestion(name, limit)}")


def check_name(name: object, what: str) -> str:
    """``name`` if it is a valid ``what``.

    Raises:
        UsageError: naming what is wrong, with a valid name to use instead where one is near.
    """
    problem = name_problem(name, what)
    if problem is not None:
        raise UsageError(problem)
    assert isinstance(name, str)
    return name


def check_tag(tag: object, what: str = "dataset tag") -> str:
    """``tag`` if it is a valid dataset tag (a name other than ``latest``).

    Raises:
        UsageError: naming what is wrong.
    """
    if tag == _LATEST or (isinstance(tag, str) and _VERSION.fullmatch(tag)):
        raise UsageError(f"{what} {shown(tag)} is not allowed: numbers and '{_LATEST}' name "
                         "versions; pick a name that starts with a letter")
    return check_name(tag, what)


_LABEL_KEY = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9._/-]*[A-Za-z0-9])?")
_MAX_LABEL_KEY, _MAX_LABEL_VALUE = 128, 256


def check_label(key: object, value: object) -> tuple[str, str]:
    """``(key, value)`` if they make a workflow label (``--label k=v``, ``list --label``).

    A key is letters, digits and ``._/-`` (Kubernetes-like: ``team``, ``app.example/run``),
    starting and ending with a letter or digit, at most 128 characters; a value is non-empty
    text of at most 256 characters with no control characters.

    Raises:
        UsageError: naming what is wrong.
    """
    if not isinstance(key, str) or len(key) > _MAX_LABEL_KEY or not _LABEL_KEY.fullmatch(key):
        raise UsageError(f"label key {shown(key)} is not valid: letters, digits and ._/- "
                         f"starting and ending with a letter or digit, at most "
                         f"{_MAX_LABEL_KEY} characters")
    if not isinstance(value, str) or not value or len(value) > _MAX_LABEL_VALUE \
            or any(ord(c) < 32 or ord(c) == 127 for c in value):
        raise UsageError(f"label {key}'s value {shown(value)} is not valid: non-empty text of "
                         f"at most {_MAX_LABEL_VALUE} characters, no control characters")
    return key, value


def ref_problem(ref: object, what: str = "dataset") -> str | None:
    """Why ``ref`` is not ``NAME[:TAG|VERSION|latest]``, or None."""
    if not isinstance(ref, str):
        return f"{what} reference must be a string, not {type(ref).__name__}"
    name, colon, tag = ref.partition(":")
    problem = name_problem(name, f"{what} name")
    if problem is not None or not colon:
        return problem
    if tag == _LATEST or _VERSION.fullmatch(tag):
        return None
    return name_problem(tag, f"{what} tag or version")


def parse_ref(ref: object, what: str = "dataset") -> tuple[str, str | None]:
    """``NAME[:TAG|VERSION|latest]`` → (name, tag or version text, or None).

    Raises:
        UsageError: naming what is wrong.
    """
    problem = ref_problem(ref, what)
    if problem is not None:
        raise UsageError(problem)
    assert isinstance(ref, str)
    name, _, tag = ref.partition(":")
    return name, tag or None


# The OCI image reference grammar (github.com/distribution/reference, regexp.go):
# [HOST[:PORT]/]PATH[:TAG][@DIGEST], PATH lower-case components joined by '/'.
_PATH_PART = r"[a-z0-9]+(?:(?:[._]|__|-+)[a-z0-9]+)*"
_HOST_PART = r"(?:[a-zA-Z0-9]|[a-zA-Z0-9][a-zA-Z0-9-]*[a-zA-Z0-9])"
_HOST = rf"(?:{_HOST_PART}(?:\.{_HOST_PART})*|\[[a-fA-F0-9:]+\])(?::[0-9]+)?"
_IMAGE_RE = re.compile(
    rf"(?P<name>(?:{_HOST}/)?{_PATH_PART}(?:/{_PATH_PART})*)"
    r"(?::[\w][\w.-]{0,127})?"
    r"(?:@(?P<algo>[A-Za-z][A-Za-z0-9]*(?:[-_+.][A-Za-z][A-Za-z0-9]*)*)"
    r":(?P<hex>[0-9a-fA-F]{32,}))?", re.ASCII)
_MAX_IMAGE_NAME = 255  # the grammar's limit on HOST/PATH
_MAX_IMAGE = _MAX_IMAGE_NAME + 1 + 128 + 1 + 7 + 1 + 128  # with a tag and a sha512 digest
_DIGEST_HEX = {"sha256": 64, "sha512": 128}
_IMAGE_FORM = ("write [REGISTRY[:PORT]/]NAME[:TAG][@sha256:HEX], NAME in lower case, like "
               "nvcr.io/nvidia/pytorch:24.01-py3")


def image_problem(image: str) -> str | None:
    """Why ``image`` is not a container image reference of the OCI grammar, or None.

    What passes can go to an engine's CLI as one word: it never starts with ``-``, holds no
    whitespace, control character, quote or shell character.
    """
    if not image:
        return "an image reference must not be empty"
    if image.startswith("-"):
        return f"{shown(image)} starts with '-' (an engine would read it as an option)"
    if any(c.isspace() or ord(c) < 32 or ord(c) == 127 for c in image):
        return f"{shown(image)} holds whitespace or a control character"
    match = _IMAGE_RE.fullmatch(image) if len(image) <= _MAX_IMAGE else None
    if len(image) > _MAX_IMAGE or (match is not None and len(match["name"]) > _MAX_IMAGE_NAME):
        return (f"{shown(image)} is too long: a repository name has at most "
                f"{_MAX_IMAGE_NAME} characters")
    if match is None:
        return f"{shown(image)} is not an image reference: {_IMAGE_FORM}"
    want = _DIGEST_HEX.get((match["algo"] or "").lower())
    if want is not None and len(match["hex"]) != want:
        return f"{shown(image)} has a {match['algo']} digest of {want} hex digits"
    return None


def workflow_id_problem(workflow_id: object) -> str | None:
    """Why ``workflow_id`` cannot be one, or None.

    Ids are ``NAME-N``; a bare name passes too, so that a lookup can suggest its ids.
    """
    return name_problem(workflow_id, "workflow id", limit=_MAX_ID)


def check_workflow_id(workflow_id: object) -> str:
    """``workflow_id`` if it could be one (see :func:`workflow_id_problem`).

    Raises:
        UsageError: naming what is wrong.
    """
    problem = workflow_id_problem(workflow_id)
    if problem is not None:
        raise UsageError(problem)
    assert isinstance(workflow_id, str)
    return workflow_id


def check_worker_name(name: object, *, reserved: tuple[str, ...] = ()) -> str:
    """``name`` if it can name a remote worker (a zenoh key chunk, a node id, a log label).

    Args:
        name: what the worker calls itself (or a client its blob source).
        reserved: names taken by the server itself (its own pool's node, its blobs).

    Raises:
        UsageError: naming what is wrong.
    """
    if not isinstance(name, str):
        raise UsageError(f"a worker name must be a string, not {type(name).__name__}")
    if len(name) > _MAX_WORKER or not _WORKER_RE.fullmatch(name) or name in reserved:
        taken = f" other than {', '.join(map(repr, reserved))}" if reserved else ""
        raise UsageError(f"worker name {shown(name)} is not valid: use letters, digits, '.', "
                         f"'-' and '_', starting and ending with a letter or digit, at most "
                         f"{_MAX_WORKER} characters{taken}")
    return name


def object_ref(obj: Any) -> str:
    """The ``module:attr`` reference under which ``obj``'s module holds it (a task type).

    A ``@task_type`` function is named by its wrapped function's module. Found in the module's
    globals, so a worker can import it by that reference.

    Raises:
        UsageError: the object is not in its module's globals, or lives in ``__main__`` (a
            worker cannot import the script being run).
    """
    fn = getattr(obj, "fn", None)
    module_name = getattr(fn, "__module__", None) or getattr(obj, "__module__", None)
    if module_name is None and not inspect.isclass(obj):
        module_name = type(obj).__module__
    if module_name == "__main__":
        raise UsageError("task types defined in the script being run cannot be imported by "
                         "the worker; move them into a module next to it (e.g. tasks.py) "
                         "and import them from there")
    module = sys.modules.get(module_name or "")
    for attr, value in vars(module).items() if module is not None else ():
        if value is obj:
            return f"{module_name}:{attr}"
    raise UsageError(f"cannot find {obj!r} in its module '{module_name}'; pass the type as "
                     "a 'module:attr' string")
