"""An attempt's data in and out.

Before it runs, ``url`` inputs and private copies of its artifact inputs; after a successful exit,
the last checkpoint, promotion, ingest into the artifact store, and ``url`` output uploads.

Runs on the pool's I/O threads. Inputs land beside the attempt folder (kept apart because
preparing an attempt again clears its folder) and reach the command through
``{{input:N}}``/``{{input:<name>}}``:

- ``<attempt>.inputs/<index>/``: a ``url`` input, downloaded;
- ``<attempt>/inputs/<input name>/``: an artifact input (an upstream task's output,
  another workflow's, a dataset version), copied for this attempt alone from the blob store
  and checked against its digests (``ArtifactStore.copy_tree``: a reflink where the
  filesystem can share data, else a copy). A task may change its copy freely; no blob and
  no other reader sees it. A blob that no longer matches its digest fails the attempt's
  start. Copies over 1 MiB are deleted when the attempt ends.

  In a sandbox (``Paths.linked_inputs``) the same folder holds hard links of the checked
  blobs instead of copies (``ArtifactStore.link_checked``): the sandbox binds the attempt's
  folder read-only (``osmo.runtime.process.sandboxed.attempt_view``), so the task cannot
  change them, and no data is copied.

Outputs are uploaded from the promoted ``output/`` folder after it was ingested; a failed
upload fails the attempt (its output is never handed downstream), and the URL's completion
marker is only written when every file arrived (see ``osmo.urls``).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import Protocol

from osmo.artifacts import ArtifactStore, Manifest
from osmo.artifacts.fsops import make_dirs, remove_tree
from osmo.artifacts.store import DEFAULT_MAX_FILES
from osmo.errors import OsmoError
from osmo.layout import AttemptDirs
from osmo.runtime.api import HOST_PATHS, Launch, Paths
from osmo.scheduler.types import PrepareAttempt
from osmo.spec.model import TaskSpec
from osmo.urls import for_url
from osmo.worker.secrets import Secrets
from osmo.worker.workdir import prepare, promote, remove_secret_files

__all__ = ["CredentialLookup", "DeliveryError", "InputCopies", "ManifestLookup", "copy_inputs",
           "deliver", "fetch_inputs", "make_ready", "plan_input_copies", "push_outputs"]

CredentialLookup = Callable[[str], Mapping[str, str] | None]
ManifestLookup = Callable[[str], Manifest | None]
"""An input reference → the manifest of the artifact it names (None: not an artifact)."""
InputCopies = list[tuple[Manifest, Path]]
"""The copies an attempt's artifact inputs need: (manifest, folder to write)."""

_KEEP_COPIES = 1 << 20  # input copies up to this size stay with the attempt's folder


def fetch_inputs(cmd: PrepareAttempt, task: TaskSpec, dirs: AttemptDirs,
                 credential_for: CredentialLookup | None) -> PrepareAttempt:
    """Download every ``url`` input; returns ``cmd`` with their folders as inputs.

    Raises:
        OsmoError: a download failed (``UrlError``) or a URL is malformed (``UsageError``).
    """
    extra: dict[str, str] = {}
    base = dirs.url_inputs
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


def make_ready(dirs: AttemptDirs, cmd: PrepareAttempt, task: TaskSpec, *,
               env: Mapping[str, str], secrets: Secrets,
               credential_for: CredentialLookup | None, artifacts: ArtifactStore | None,
               input_manifests: ManifestLookup | None, paths: Paths = HOST_PATHS
               ) -> tuple[PrepareAttempt, Launch]:
    """Everything an attempt needs before its runtime can take it, in order.

    Its ``url`` inputs, its folder and files (``workdir.prepare``, for the ``paths`` its
    runtime shows it), its own copies of its artifact inputs (hard links of the checked
    blobs when ``paths.linked_inputs``: its runtime shows them read-only).

    Returns:
        ``cmd`` with its inputs resolved to their folders here, and its launch.

    Raises:
        OsmoError: a download, a token, a file, a credential or a blob failed (a blob that
            no longer matches its digest is ``ArtifactCorrupted``); credential files already
            written are deleted first.
        OSError: the attempt's folder cannot be written.
    """
    cmd = fetch_inputs(cmd, task, dirs, credential_for)
    cmd, copies = plan_input_copies(cmd, dirs, input_manifests if artifacts else None)
    launch = prepare(dirs, cmd, task, env, secrets, paths=paths)
    if copies and artifacts is not None:
        try:
            launch = replace(launch, scratch=copy_inputs(copies, artifacts,
                                                         links=paths.linked_inputs))
        except BaseException:
            remove_secret_files(launch)
            raise
    return cmd, launch


def plan_input_copies(cmd: PrepareAttempt, dirs: AttemptDirs,
                      manifest_of: ManifestLookup | None) -> tuple[PrepareAttempt, InputCopies]:
    """Where the attempt's own copy of each artifact input goes (``inputs/<input name>``).

    Returns ``cmd`` with those folders as its inputs, and what :func:`copy_inputs` must write.
    """
    if manifest_of is None or not cmd.inputs:
        return cmd, []
    names: dict[str, list[str]] = {}
    for key, ref in cmd.inputs.items():
        names.setdefault(ref, []).append(key)
    plan: InputCopies = []
    copies: dict[str, str] = {}
    for ref, keys in names.items():
        manifest = manifest_of(ref)
        if manifest is None:
            continue  # a downloaded url input (already private), or nothing osmo stored
        dest = dirs.inputs / _folder_name(keys, manifest)
        plan.append((manifest, dest))
        copies[ref] = str(dest)
    return (replace(cmd, inputs={key: copies.get(ref, ref) for key, ref in cmd.inputs.items()}),
            plan)


def copy_inputs(plan: InputCopies, artifacts: ArtifactStore, *,
                links: bool = False) -> tuple[Path, ...]:
    """Write the planned copies (after the attempt's folder was made).

    ``links``: checked hard links instead of copies (a sandboxed task: it cannot write them).
    Returns those to delete when the attempt ends: copies over 1 MiB (small ones stay with the
    attempt's folder; links hold no space of their own, and stay).

    Raises:
        ArtifactCorrupted: a blob is missing or no longer matches its digest.
    """
    if plan:
        try:  # the attempt's folder was just made: one mkdir, not a walk up (make_dirs)
            os.mkdir(plan[0][1].parent)
        except FileExistsError:
            pass
        except FileNotFoundError:
            make_dirs(plan[0][1].parent)
    for manifest, dest in plan:
        (artifacts.link_checked if links else artifacts.copy_tree)(manifest, dest)
    return () if links else tuple(dest for manifest, dest in plan
                                  if manifest.size > _KEEP_COPIES)


def _folder_name(keys: list[str], manifest: Manifest) -> str:
    """The input's name (the upstream task's, for a task input), so paths read well."""
    for key in keys:
        name = key.replace("/", "_")
        if name not in ("", ".", "..") and not name.isdigit() and len(name) < 200:
            return name
    return f"m{manifest.digest[7:23]}"


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
            artifacts: ArtifactStore | None, credential_for: CredentialLookup | None,
            max_bytes: int | None = None,
            max_files: int | None = DEFAULT_MAX_FILES) -> tuple[str, str | None]:
    """Finish a successful attempt's outputs, in order (I/O thread).

    Last checkpoint upload, promotion of ``output.partial`` to ``output``, ingest (within
    ``max_bytes`` and ``max_files``), ``url`` uploads.

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
        manifest = artifacts.ingest(Path(ref), max_bytes=max_bytes,
                                    max_files=max_files) if artifacts else None
    except (OSError, OsmoError) as exc:
        raise DeliveryError(f"outputs could not be promoted: {exc}") from exc
    try:
        push_outputs(task, Path(ref), credential_for)
    except (OSError, OsmoError) as exc:
        raise DeliveryError(f"upload of outputs failed: {exc}") from exc
    return ref, manifest.to_json() if manifest else None
