"""The exception tree of osmo. Every public exception derives from :class:`OsmoError`.

::

    OsmoError                       exit code 1 unless a subclass says otherwise
    ├── SpecError                   a workflow spec is invalid (exit 2); carries every Diagnostic
    ├── UsageError                  bad command-line or SDK arguments (exit 2)
    ├── NotFoundError               a workflow, task or attempt that does not exist (exit 2)
    ├── SubmitError                 a valid spec the server refuses (e.g. no pool fits) (exit 2)
    ├── ServerUnreachable           no server answered (exit 3)
    ├── InfrastructureError         the server, store or a worker failed (exit 3)
    │   └── ArtifactCorrupted       a stored blob does not match its digest (osmo.artifacts)
    ├── OutputRejected              an output holds what cannot be stored (osmo.artifacts)
    └── WorkflowFailed              a waited-for workflow ended in a failed status (exit 1)

    UsageError also has ``RecordError`` (an unreadable MCAP file, ``osmo.record``);
    ``StartError``/``PrepareError``/``SecretError`` (``osmo.runtime``/``osmo.worker``) derive
    from OsmoError and become a task's FAILED_START_ERROR, never a CLI error.

Third-party errors (zenoh, sqlite3, yaml, jinja2) are translated into these at the one module
that imports each library; callers never see a foreign exception for a user mistake.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "Diagnostic",
    "InfrastructureError",
    "NotFoundError",
    "OsmoError",
    "ServerUnreachable",
    "SpecError",
    "SubmitError",
    "UsageError",
    "WorkflowFailed",
]


class OsmoError(Exception):
    """Root of every error osmo raises on purpose.

    Attributes:
        exit_code: the documented process exit code the CLI uses for this error.
    """

    exit_code: int = 1


@dataclass(frozen=True)
class Diagnostic:
    """One problem found in a spec, at a place in a file.

    Attributes:
        file: the spec's file name (or ``<builder>``/``<string>``).
        line: 1-based line, 0 when unknown.
        col: 1-based column, 0 when unknown.
        message: what is wrong and, where known, how to fix it.
    """

    file: str
    line: int
    col: int
    message: str

    def __str__(self) -> str:
        if self.line:
            return f"{self.file}:{self.line}:{self.col}: {self.message}"
        return f"{self.file}: {self.message}"


class SpecError(OsmoError):
    """A spec was rejected; ``diagnostics`` lists every problem found, in file order."""

    exit_code = 2

    def __init__(self, diagnostics: list[Diagnostic]) -> None:
        self.diagnostics = sorted(diagnostics, key=lambda d: (d.file, d.line, d.col))
        super().__init__("\n".join(str(d) for d in self.diagnostics))


class UsageError(OsmoError):
    """Arguments to a command or SDK call are wrong."""

    exit_code = 2


class MissingExtra(UsageError):
    """A plugin's optional dependency is not installed; the message names the pip extra."""


class NotFoundError(OsmoError):
    """A named workflow, task, retry or attempt does not exist."""

    exit_code = 2


class SubmitError(OsmoError):
    """The server refused a valid spec (for example: no pool can ever fit a task)."""

    exit_code = 2


class ServerUnreachable(OsmoError):
    """No osmo server answered at the configured endpoint."""

    exit_code = 3


class InfrastructureError(OsmoError):
    """The server, its state store or a worker failed in a way that is not the user's fault."""

    exit_code = 3


class WorkflowFailed(OsmoError):
    """A workflow that was waited for ended in a status other than COMPLETED.

    Attributes:
        workflow_id: the workflow's id.
        status: its final status name.
    """

    exit_code = 1

    def __init__(self, workflow_id: str, status: str) -> None:
        self.workflow_id = workflow_id
        self.status = status
        super().__init__(f"workflow {workflow_id} ended {status}")
