"""Pulling an image with the engine's CLI: progress line by line, credentials for the pull only.

:func:`pull_image` runs ``pull_argv``'s command and hands each line the engine prints to a
callback as it comes (a task's log shows a long pull while it happens). A registry
credential is written (``registry_config``) into a 0600 auth file of a private folder that
the pull reads and that is deleted when the pull ends; the password is in no argv,
environment, log line or message (each line and the error are scrubbed of it).

Used through ``osmo.runtime.container.ContainerEngine.pull``.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path

from osmo.runtime.container.run import (
    ContainerError,
    EngineInfo,
    RegistryAuth,
    pull_argv,
    registry_config,
)

__all__ = ["ImageError", "pull_image"]


class ImageError(ContainerError):
    """An image is missing and cannot be pulled: ``image 'x' not found: <why>``."""


def pull_image(engine: EngineInfo, env: Mapping[str, str], image: str, *,
               progress: Callable[[str], None] | None = None,
               auth: RegistryAuth | None = None) -> None:
    """Pull ``image`` with ``engine`` (its CLI's environment ``env``).

    Raises:
        ImageError: the pull failed (the engine's reason; never a password).
    """
    with tempfile.TemporaryDirectory(prefix="osmo-registry-") as folder:
        config = Path(folder) if auth is not None else None
        secrets = [auth.password] if auth is not None else []
        try:
            if auth is not None and config is not None:
                _write_private(*registry_config(engine, auth, config))
            argv, extra = pull_argv(engine, image, config)
            _stream(argv, {**env, **extra}, progress, secrets)
        except ContainerError as exc:
            raise ImageError(_scrub(f"image '{image}' not found: not on this node and the "
                                    f"pull failed: {exc}", secrets)) from None


def _stream(argv: list[str], env: Mapping[str, str], progress: Callable[[str], None] | None,
            secrets: list[str]) -> None:
    """Run ``argv``; each non-empty line of its output (scrubbed) goes to ``progress``."""
    try:
        proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, env=dict(env))
    except OSError as exc:
        raise ContainerError(f"cannot run {argv[0]}: {exc.strerror or exc}") from exc
    last = ""
    assert proc.stdout is not None
    with proc.stdout:
        for raw in proc.stdout:
            line = _scrub(raw.decode(errors="replace").rstrip(), secrets)
            if line.strip():
                last = line.strip()
                if progress is not None:
                    progress(line)
    if proc.wait() != 0:
        raise ContainerError(last.removeprefix("Error: ") or f"exit code {proc.returncode}")


def _write_private(path: Path, text: str) -> None:
    """A new 0600 file (never through a planted file or symlink)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                 0o600)
    with os.fdopen(fd, "w") as out:
        out.write(text)


def _scrub(text: str, secrets: list[str]) -> str:
    for secret in secrets:
        if secret:
            text = text.replace(secret, "***")
    return text
