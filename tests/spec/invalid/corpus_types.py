"""Task types the invalid-spec corpus refers to as ``corpus_types:NAME`` (imported from this
folder, as a workflow's own ``module:attr`` types are)."""

from osmo import Param, task_type


@task_type(version="3", params={
    "steps": Param(int, help="how many steps"),
    "rate": Param(float, default=0.5, min=0.0, max=1.0),
    "mode": Param(str, default="fast", choices=("fast", "exact")),
    "tags": Param(list, default=[]),
})
def train(ctx):  # type: ignore[no-untyped-def]
    """A type with every kind of parameter check."""


@task_type(version="1", resources={"gpus": 1})
def greedy(ctx):  # type: ignore[no-untyped-def]
    """Declares a resource key the spec does not know."""


not_a_type = object()
