"""Data URLs of an attempt: downloading ``url`` inputs before it runs, uploading after.

Runs on the pool's I/O threads. Inputs land in ``<attempt>.inputs/<index>/`` beside the
attempt folder (kept apart because preparing an attempt again clears its folder) and reach
the command through ``{{input:N}}``/``{{input:<url>}}``. Outputs are uploaded from the
promoted ``output/`` folder after it was ingested; a failed upload fails the attempt (its
output is never handed downstream), and the URL's completion marker is only written when
every file arrived (see ``osmo.urls``).
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path

from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import TaskSpec
from osmo.urls import for_url
from osmo.worker.workdir import AttemptDirs

__all__ = ["CredentialLookup", "fetch_inputs", "push_outputs"]

CredentialLookup = Callable[[str], Mapping[str, str] | None]


def fetch_inputs(cmd: PrepareAttempt, task: TaskSpec, dirs: AttemptDirs,
                 credential_for: CredentialLookup | None) -> PrepareAttempt:
    """Download every ``url`` input; returns ``cmd`` with their folders as inputs.

    Raises:
        OsmoError: a download failed (``UrlError``) or a URL is malformed (``UsageError``).
    """
    extra: dict[str, str] = {}
    base = dirs.root.with_name(f"{dirs.root.name}.inputs")
    for index, spec in enumerate(task.inputs):
        if spec.url is None:
            continue
        dest = base / str(index)
        if dest.exists():
            shutil.rmtree(dest)
        dest.parent.mkdir(parents=True, exist_ok=True)
        remote = for_url(spec.url, credential_for(spec.url) if credential_for else None)
        remote.download(dest, regex=spec.regex)
        extra[spec.url] = extra[str(index)] = str(dest)
    return replace(cmd, inputs={**cmd.inputs, **extra}) if extra else cmd


def push_outputs(task: TaskSpec, folder: Path, credential_for: CredentialLookup | None) -> None:
    """Upload ``folder`` to every ``url`` output of ``task``.

    Raises:
        OsmoError: an upload failed; nothing is marked complete at that URL.
    """
    for spec in task.outputs:
        if spec.url is not None:
            remote = for_url(spec.url, credential_for(spec.url) if credential_for else None)
            remote.upload(folder, regex=spec.regex)
