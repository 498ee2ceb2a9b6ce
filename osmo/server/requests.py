"""The engine's typed API: what API handlers and executors may ask of it (``Engine.ask``).

A request is applied on the engine thread, in the batch of events it arrives with, and its
answer is given after that batch is committed. What applying a request raises (a
``SubmitError`` for a workflow that can never fit) goes back to the asker, and nothing of
that request is stored. No handler touches the engine's state; the requests and what each
one answers:

- :class:`SubmitWorkflow` → the new workflow's id;
- ``osmo.scheduler.CancelWorkflow`` (the scheduler's own event) → None;
- :class:`TagDataset` → None;
- :class:`TagWorkflow` → the workflow's tags after the change;
- :class:`AddDatasetVersion` → the new version's number;
- :class:`AttemptsOn` → the ids of the attempts placed on a node (how the hub reconciles a
  worker that registers again);
- :class:`ListNodes` → every node with the resources its attempts hold;
- :class:`WaitReasons` → why each waiting task of a workflow waits (``Scheduler.waiting``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from osmo.artifacts import Manifest
from osmo.scheduler.types import CancelWorkflow
from osmo.spec.model import WorkflowSpec
from osmo.spec.stored import StoredSpec
from osmo.store.submission import Submission

__all__ = ["AddDatasetVersion", "AttemptsOn", "ListNodes", "Request", "SubmitWorkflow",
           "TagDataset", "TagWorkflow", "WaitReasons"]


@dataclass(frozen=True)
class SubmitWorkflow:
    """Create workflow ``<spec.name>-N`` from a checked spec.

    Attributes:
        spec: the spec, task types resolved (parsed once, by the submit handler).
        stored: the same spec as the store keeps it.
        options: how it was submitted (pool and labels as they apply to it).
        reused: task name → output of an earlier run to reuse (``osmo restart``).
    """

    spec: WorkflowSpec
    stored: StoredSpec
    options: Submission
    reused: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class TagDataset:
    """Point ``tag`` of dataset ``name`` at ``version`` (moving it if it pointed elsewhere)."""

    name: str
    tag: str
    version: int


@dataclass(frozen=True)
class TagWorkflow:
    """Add ``add`` to workflow ``workflow_id``'s tags and take ``remove`` away (checked names)."""

    workflow_id: str
    add: tuple[str, ...] = ()
    remove: tuple[str, ...] = ()


@dataclass(frozen=True)
class AddDatasetVersion:
    """Make the next version of dataset ``name`` hold ``manifest`` (an upload)."""

    name: str
    manifest: Manifest
    metadata: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class AttemptsOn:
    """The attempts placed on ``node_id`` that have not sent their final report."""

    node_id: str


@dataclass(frozen=True)
class ListNodes:
    """Every known node with what its attempts hold.

    ``[(Node, Capacity used, {platform: Capacity its attempts of that platform hold})]``.
    """


@dataclass(frozen=True)
class WaitReasons:
    """Task name → ``osmo.scheduler.Waiting`` for the waiting tasks of ``workflow_id``.

    ``names``: only for these tasks (None: every one).
    """

    workflow_id: str
    names: frozenset[str] | None = None


Request = (SubmitWorkflow | CancelWorkflow | TagDataset | TagWorkflow | AddDatasetVersion
           | AttemptsOn | ListNodes | WaitReasons)
