"""Every path under an osmo home, in one place.

``OSMO_HOME`` (the server's and a client's) and a remote worker's home share one layout::

    <home>/
        state.db              the state store (SQLite, WAL)
        server.json           the running server's endpoint and pid (written atomically)
        server.lock           held (flock) by the running server for its life
        server.log            a background server's own output
        server-options.json   the options of the last explicit ``osmo server start`` (0600)
        server.sock           the local server's Unix socket (owner-only: see ``server_socket``)
        auth/admin.token      the home owner's admin token (0600; used by the local CLI/SDK)
        auth/notice.key       the server's Ed25519 key that signs its notices (0600)
        applying.json         ids of the attempt reports being applied (the quarantine file)
        crashes.json          tasks a server died applying a report of, and how often
        profile.json          the client profile (``osmo profile set``)
        worker.json           a remote worker's health (in the worker's home)
        artifacts/            the content-addressed store (see :class:`BlobDirs`)
        client/artifacts/     a client's own store: uploads and downloads pass through it
        datasets/<name>/<version>[-<variant>]/   materialized dataset versions
        runs/<workflow_id>/
            run.mcap          the workflow's run record
            <task>/<retry>/   one attempt's private folder (see :class:`AttemptDirs`)
            <task>/<retry>.inputs/<index>/   its downloaded ``url`` inputs

The objects here only name paths: they create nothing and read nothing, so any layer may use
them (the bottom layer; imports only ``osmo.errors``). Workers make and fill attempt folders
(``osmo.worker.workdir``), the artifact store its blobs (``osmo.artifacts``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

from osmo.errors import UsageError

__all__ = ["AttemptDirs", "BlobDirs", "Home"]

_MAX_SOCKET_PATH = 100  # sun_path holds 108 bytes with its NUL; leave room


@dataclass(frozen=True)
class AttemptDirs:
    """One attempt's folder, ``runs/<workflow_id>/<task>/<retry>/``.

    What it holds::

        work/            the command's working folder (cwd)
        inputs/<name>/   the attempt's own checked copy of each artifact input
        files/           private root for absolute ``files:`` paths and credential mounts
        output.partial/  what ``{{output}}`` and ``OSMO_OUTPUT`` point to while running
        output/          the same folder after promotion (success only)
        log.txt          the attempt's log records (``osmo.worker.logs``)
        task.json        a typed task's context file (``osmo.worker.launch``)
    """

    root: Path

    @functools.cached_property
    def work(self) -> Path:
        """The command's working folder."""
        return self.root / "work"

    @functools.cached_property
    def files(self) -> Path:
        """Private root of absolute ``files:`` paths."""
        return self.root / "files"

    @functools.cached_property
    def inputs(self) -> Path:
        """The attempt's own copies of its artifact inputs, one folder per input."""
        return self.root / "inputs"

    @property
    def url_inputs(self) -> Path:
        """Its downloaded ``url`` inputs, one folder per input index.

        Beside the attempt's folder: preparing the attempt again clears that folder, not these.
        """
        return self.root.with_name(f"{self.root.name}.inputs")

    @functools.cached_property
    def output_partial(self) -> Path:
        """The output folder while the command runs."""
        return self.root / "output.partial"

    @functools.cached_property
    def output(self) -> Path:
        """The output folder after promotion."""
        return self.root / "output"

    @functools.cached_property
    def log(self) -> Path:
        """The attempt's log file."""
        return self.root / "log.txt"

    @property
    def context(self) -> Path:
        """A typed task's context file."""
        return self.root / "task.json"


@dataclass(frozen=True)
class BlobDirs:
    """An artifact store's folder: its blobs and a scratch folder.

    ``blobs/sha256/<first 2 hex>/<other 62 hex>``, and ``tmp/``, where blobs are written before they
    are renamed into place.
    """

    root: Path

    @property
    def blobs(self) -> Path:
        """The folder of every blob."""
        return self.root / "blobs" / "sha256"

    @property
    def tmp(self) -> Path:
        """Scratch space on the same filesystem as the blobs."""
        return self.root / "tmp"

    def blob(self, hex_digest: str) -> Path:
        """Where the blob with this (already checked) sha256 hex digest lives."""
        return self.blobs / hex_digest[:2] / hex_digest[2:]


@dataclass(frozen=True)
class Home:
    """The paths of one osmo home (see the module docstring)."""

    root: Path

    @property
    def state_db(self) -> Path:
        """The state store."""
        return self.root / "state.db"

    @property
    def server_info(self) -> Path:
        """The running server's endpoint and pid."""
        return self.root / "server.json"

    @property
    def server_lock(self) -> Path:
        """Held by the running server."""
        return self.root / "server.lock"

    @property
    def server_log(self) -> Path:
        """A background server's output."""
        return self.root / "server.log"

    @property
    def server_options(self) -> Path:
        """The options of the last explicit start, reused by an automatic start."""
        return self.root / "server-options.json"

    @property
    def server_socket(self) -> Path:
        """The Unix socket the local server listens on and the local CLI connects to.

        ``server.sock`` in the home, unless that path is too long for a socket address
        (about 108 bytes on Linux): then a short name under ``/tmp/osmo-<uid>/`` (a folder
        that must be its owner's only; the server creates and checks it).
        """
        path = self.root.absolute() / "server.sock"
        if len(str(path).encode()) < _MAX_SOCKET_PATH:
            return path
        import hashlib
        import os

        digest = hashlib.sha256(str(self.root.absolute()).encode()).hexdigest()[:16]
        return Path(f"/tmp/osmo-{os.geteuid()}") / f"{digest}.sock"

    @property
    def auth(self) -> Path:
        """The folder of the home owner's tokens (0700)."""
        return self.root / "auth"

    @property
    def admin_token(self) -> Path:
        """The home owner's admin token, created by the server at first start (0600)."""
        return self.auth / "admin.token"

    @property
    def notice_key(self) -> Path:
        """The server's key for signing its broadcast notices (``osmo.transport.seal``)."""
        return self.auth / "notice.key"

    @property
    def applying(self) -> Path:
        """The quarantine file (``osmo.server.recovery.InFlight``)."""
        return self.root / "applying.json"

    @property
    def crashes(self) -> Path:
        """Tasks a server died while applying a report of (``InFlight.strike``)."""
        return self.root / "crashes.json"

    @property
    def profile(self) -> Path:
        """The client profile."""
        return self.root / "profile.json"

    @property
    def procs(self) -> Path:
        """The record of the commands a pool runs (``osmo.worker.procs``)."""
        return self.root / "procs"

    @property
    def worker_health(self) -> Path:
        """A remote worker's health file."""
        return self.root / "worker.json"

    @property
    def artifacts(self) -> Path:
        """The artifact store of this home."""
        return self.root / "artifacts"

    @property
    def client_artifacts(self) -> Path:
        """A client's own artifact store."""
        return self.root / "client" / "artifacts"

    @property
    def runs(self) -> Path:
        """Every workflow's folder."""
        return self.root / "runs"

    def run(self, workflow_id: str) -> Path:
        """The folder of one workflow's attempts and run record."""
        return self.runs / _component(workflow_id)

    def run_record(self, workflow_id: str) -> Path:
        """Where the run record of ``workflow_id`` lives."""
        return self.run(workflow_id) / "run.mcap"

    def attempt(self, workflow_id: str, task: str, retry: int) -> AttemptDirs:
        """The folder of retry ``retry`` of ``task`` in ``workflow_id``.

        Raises:
            UsageError: a name that cannot be one path component.
        """
        return AttemptDirs(self.runs.absolute() / _component(workflow_id) / _component(task)
                           / str(int(retry)))

    def attempt_of(self, attempt_id: str) -> AttemptDirs | None:
        """The folder of attempt ``<workflow>:<task>:<retry>``, or None for a malformed id."""
        parts = attempt_id.rsplit(":", 2)
        if len(parts) != 3 or not parts[2].isdigit():
            return None
        try:
            return self.attempt(parts[0], parts[1], int(parts[2]))
        except UsageError:
            return None

    @property
    def datasets(self) -> Path:
        """Every materialized dataset version."""
        return self.root / "datasets"

    def dataset_version(self, name: str, version: int, variant: str | None = None) -> Path:
        """The folder of ``name``'s version ``version`` (``variant``: a selection of it)."""
        suffix = f"-{variant}" if variant else ""
        return self.datasets / _component(name) / f"{int(version)}{suffix}"


def _component(name: str) -> str:
    """``name`` if it is usable as one path component.

    Raises:
        UsageError: empty, ``.``, ``..`` or holding a ``/``.
    """
    if not name or "/" in name or name in (".", ".."):
        raise UsageError(f"unusable name for a folder: {name!r}")
    return name
