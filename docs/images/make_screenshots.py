"""Regenerate the terminal pictures of the docs from a real run.

Runs ``osmo submit workflows/hello-pipeline.yaml --wait`` and ``osmo query`` through osmo's own
CLI (``osmo.cli.main.main``) against a fresh server in a temporary ``OSMO_HOME``, with the
CLI's console swapped for a recording ``rich`` console that behaves as a 100-column terminal
(so ``--wait`` draws its live view). The live view is redrawn many times; the picture keeps
what a terminal shows at the end: the lines before the live view and its last frame.

    python docs/images/make_screenshots.py          # from the repository root

    python docs/images/make_screenshots.py --out DIR

Writes ``submit-wait.svg``, ``query.svg`` and ``submit-reuse.svg`` (the same workflow submitted
again: its tasks are reused, and the output says so) to ``docs/images`` (or DIR). Tasks run as
host processes (``OSMO_RUNTIME=process``), as on a machine without a container engine.
"""

from __future__ import annotations

import io
import os
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
OUT = REPO / "docs" / "images"
WIDTH = 100


def _console():  # type: ignore[no-untyped-def]
    from rich.console import Console

    return Console(record=True, force_terminal=True, color_system="truecolor", width=WIDTH,
                   file=io.StringIO(), highlight=False)


def _last_frame(console) -> None:  # type: ignore[no-untyped-def]
    """Keep what a terminal shows at the end.

    That is the lines before the live view, its last frame (what follows the last redraw,
    which erases the previous frame) and what follows it.
    """
    buffer = console._record_buffer
    controls = [i for i, seg in enumerate(buffer) if seg.control]
    if not controls:
        return
    redraws = [i for i in controls if any(c[0].name == "ERASE_IN_LINE" for c in buffer[i].control)]
    start = redraws[-1] if redraws else controls[0]
    end = next((i for i in controls if i > start), len(buffer))
    buffer[:] = buffer[:controls[0]] + buffer[start + 1:end] + buffer[controls[-1] + 1:]


def _run(argv: list[str], title: str, out: Path) -> str:
    from osmo.cli import render
    from osmo.cli.main import main

    console = _console()
    render.console._real = console
    code = main(argv)
    if code != 0:
        raise SystemExit(f"osmo {' '.join(argv)} exited {code}")
    _last_frame(console)
    # Lines printed with soft wrap (the reuse notice) are wrapped by a terminal, not by rich:
    # print the recording again into a console of the same width, which wraps them.
    from rich.text import Text

    shown = Text()
    for segment in console._record_buffer:
        shown.append(segment.text, segment.style)
    screen = _console()
    screen.print(shown, end="", overflow="fold")
    screen.save_svg(str(out), title=title)
    return shown.plain


def main(argv: list[str] | None = None) -> None:
    """Make the pictures from one real run."""
    args = sys.argv[1:] if argv is None else argv
    out = Path(args[args.index("--out") + 1]).resolve() if "--out" in args else OUT
    with tempfile.TemporaryDirectory() as tmp:
        home = Path(tmp) / "home"
        os.environ.update(OSMO_HOME=str(home), OSMO_RUNTIME="process")
        os.environ.pop("OSMO_SERVER", None)
        os.chdir(REPO)
        sys.path.insert(0, str(REPO))
        from osmo.cli.main import main as osmo

        submit = ["submit", "workflows/hello-pipeline.yaml", "--wait"]
        try:
            text = _run(submit, "osmo " + " ".join(submit), out / "submit-wait.svg")
            wf_id = text.split("Workflow ID - ", 1)[1].split()[0]
            _run(["query", wf_id], f"osmo query {wf_id}", out / "query.svg")
            _run(submit, "osmo " + " ".join(submit) + "   # again", out / "submit-reuse.svg")
        finally:
            osmo(["server", "stop"])
    print(f"wrote submit-wait.svg, query.svg and submit-reuse.svg to {out}")


if __name__ == "__main__":
    main()
