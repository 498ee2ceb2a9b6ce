"""An attempt's data in and out: ``url`` inputs before it runs; after a successful exit, the
last checkpoint, promotion, ingest into the artifact store, and ``url`` output uploads.

Runs on the pool's I/O threads. Inputs land in ``<attempt>.inputs/<index>/`` beside the
attempt folder (kept apart because preparing an attempt again clears its folder) and reach
the command through ``{{input:N}}``/``{{input:<url>}}``. Outputs are uploaded from the
promoted ``output/`` folder after it was ingested; a failed upload fails the attempt (its
output is never handed downstream), and the URL's completion marker is only written when
every file arrived (see ``osmo.urls``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import Protocol

from osmo.artifacts import ArtifactStore
from osmo.artifacts.fsops import remove_tree
from osmo.errors import OsmoError
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import TaskSpec
from osmo.urls import for_url
from osmo.worker.workdir import AttemptDirs, promote

__all__ = ["CredentialLookup", "DeliveryError", "deliver", "fetch_inputs", "push_outputs"]

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
        remove_tree(dest)
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


class DeliveryError(OsmoError):
    """A successful attempt's outputs could not be delivered; the message says which step."""


class _FinalCheckpoint(Protocol):
    def final(self) -> str | None: ...


def deliver(dirs: AttemptDirs, task: TaskSpec, *, checkpoints: _FinalCheckpoint | None,
            artifacts: ArtifactStore | None,
            credential_for: CredentialLookup | None) -> tuple[str, str | None]:
    """Finish a successful attempt's outputs, in order: last checkpoint upload, promotion of
    ``output.partial`` to ``output``, ingest, ``url`` uploads (I/O thread).

    Returns:
        the output reference and its manifest JSON (None without an artifact store).

    Raises:
        DeliveryError: a step failed; nothing of this attempt is handed downstream.
    """
    failed = checkpoints.final() if checkpoints is not None else None
    if failed is not None:
        raise DeliveryError(f"final checkpoint upload failed: {failed}")
    try:
        ref = promote(dirs)
        manifest = artifacts.ingest(Path(ref)) if artifacts else None
    except (OSError, OsmoError) as exc:
        raise DeliveryError(f"outputs could not be promoted: {exc}") from exc
    try:
        push_outputs(task, Path(ref), credential_for)
    except (OSError, OsmoError) as exc:
        raise DeliveryError(f"upload of outputs failed: {exc}") from exc
    return ref, manifest.to_json() if manifest else None
