"""Special tokens (``{{output}}``, ``{{input:N}}``, ``{{host:task}}``...) and their substitution.

Special tokens are not Jinja variables: templating must leave them intact (see
``protect``/``restore``), and they are substituted per task at run time by ``substitute``.
Pure string functions; no I/O.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping

__all__ = ["TOKEN_RE", "expand_vars", "find_tokens", "protect", "restore", "substitute"]

# {{ output }}, {{input:0}}, {{input:task-a}}, {{workflow_id}}, {{host:peer}}, {{uuid}}
TOKEN_RE = re.compile(
    r"\{\{\s*(output|workflow_id|uuid|input\s*:\s*[A-Za-z0-9_.:-]+|host\s*:\s*[A-Za-z0-9_.-]+)\s*\}\}"
)

_PLACEHOLDER = "\x00osmo-token-{}\x00"
_PLACEHOLDER_RE = re.compile("\x00osmo-token-(\\d+)\x00")


def _normal(body: str) -> str:
    """``input : a`` → ``input:a`` (spaces inside the braces are tolerated)."""
    return re.sub(r"\s*:\s*", ":", body.strip(), count=1)


def find_tokens(text: str) -> list[str]:
    """Every special token in ``text``, normalised (``output``, ``input:0``, ``host:a``...)."""
    return [_normal(m.group(1)) for m in TOKEN_RE.finditer(text)]


def protect(text: str) -> tuple[str, list[str]]:
    """Replace special tokens by opaque placeholders so a template engine leaves them alone.

    Returns:
        the protected text and the list of original token texts, for ``restore``.
    """
    saved: list[str] = []

    def keep(match: re.Match[str]) -> str:
        saved.append(match.group(0))
        return _PLACEHOLDER.format(len(saved) - 1)

    return TOKEN_RE.sub(keep, text), saved


def restore(text: str, saved: list[str]) -> str:
    """Put back the tokens that ``protect`` took out."""
    return _PLACEHOLDER_RE.sub(lambda m: saved[int(m.group(1))], text)


def substitute(text: str, resolve: Callable[[str], str | None]) -> str:
    """Replace each special token by ``resolve(normalised_token)``.

    A token for which ``resolve`` returns ``None`` is left as written.
    """

    def sub(match: re.Match[str]) -> str:
        value = resolve(_normal(match.group(1)))
        return match.group(0) if value is None else value

    return TOKEN_RE.sub(sub, text)


def expand_vars(text: str, env: Mapping[str, str]) -> str:
    """Kubernetes-style ``$(NAME)`` references in ``text``, expanded from ``env``.

    As Kubernetes expands a container's ``args``: ``$(NAME)`` becomes ``env[NAME]`` when
    NAME is defined, and stays as written when it is not; ``$$`` is an escaped ``$`` (so
    ``$$(NAME)`` is the literal ``$(NAME)``); a ``$`` before anything else, and an unclosed
    ``$(``, stay as written. One pass: an expanded value is not expanded again.
    """
    if "$" not in text:
        return text
    out: list[str] = []
    i, n = 0, len(text)
    while i < n:
        dollar = text.find("$", i)
        if dollar < 0 or dollar == n - 1:
            out.append(text[i:])
            break
        out.append(text[i:dollar])
        after = text[dollar + 1]
        if after == "$":
            out.append("$")
            i = dollar + 2
        elif after == "(" and (close := text.find(")", dollar + 2)) >= 0:
            name = text[dollar + 2:close]
            out.append(env[name] if name in env else text[dollar:close + 1])
            i = close + 1
        else:
            out.append("$" + after)
            i = dollar + 2
    return "".join(out)
