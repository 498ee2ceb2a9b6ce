"""Custom task types, written in plain Python next to the workflow that uses them.

No packaging step: ``type: tasks:numbers`` in ``workflow.yaml`` imports this module from
the workflow file's folder. A type is a function decorated with ``osmo.task_type`` or an
object with the same attributes (``Power`` below).
"""

from __future__ import annotations

from osmo import Param, TaskContext, task_type


@task_type(version="1", params={"count": Param(int, default=5, min=1, help="how many"),
                                "start": Param(int, default=1, help="the first number")})
def numbers(ctx: TaskContext) -> None:
    """Write the numbers start, start+1, ... one per line."""
    first = ctx.params["start"]
    values = range(first, first + ctx.params["count"])
    (ctx.output / "numbers.txt").write_text("".join(f"{v}\n" for v in values))
    ctx.log.info("wrote %d numbers", len(values))


class Power:
    """Raise every number of the first input to a power."""

    name = "power"
    version = "2"
    params = {"exponent": Param(int, default=2, choices=(2, 3), help="2 or 3")}
    resources = {"cpu": 1}
    extra = None
    description = "raise each input number to a power"

    def run(self, ctx: TaskContext) -> None:
        """Read ``numbers.txt`` of the first input; write ``powers.txt``."""
        numbers = (ctx.inputs[0] / "numbers.txt").read_text().split()
        powers = []
        for i, n in enumerate(numbers, 1):
            ctx.check_cancelled()
            powers.append(int(n) ** ctx.params["exponent"])
            ctx.progress(i, len(numbers))
        (ctx.output / "powers.txt").write_text("".join(f"{p}\n" for p in powers))
        ctx.log.info("sum = %d", sum(powers))


power = Power()
