"""The fenced blocks of the docs (README.md and docs/**/*.md) and what each one is.

Each block is code to run, or says on the line before it why not, in an HTML comment the
reader does not see:

- ``<!-- run by: tests/PATH.py::TEST -->``: a dedicated test reads this block from this page
  and runs it (it checks more than an exit code);
- ``<!-- not run: REASON -->``: it cannot run here (another machine, a GPU, minutes of
  training); the reason says which test covers it instead;
- ``<!-- file: NAME -->``: written to NAME in the page's folder, for the blocks after it.

Blocks without a marker run (:mod:`tests.docs.test_blocks`): ``sh`` with bash, ``python`` with
Python, a ``yaml`` workflow with ``osmo validate``. ``text`` and unlabelled blocks are output
shown to the reader, and ``mermaid`` blocks are diagrams: neither is code.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from tests.conftest import REPO

RUN_BY, NOT_RUN, FILE = "run by", "not run", "file"
SHOWN = ("", "text", "mermaid")  # output and diagrams, not code
RUNNABLE = ("sh", "python", "yaml")

_FENCE = re.compile(r"^```(\S*)\n(.*?)^```\n", re.M | re.S)
_MARKER = re.compile(r"<!-- (run by|not run|file): (.*?) -->\s*$")


@dataclass(frozen=True)
class Block:
    page: str  # relative to the repository, e.g. docs/how-to/caching.md
    line: int
    lang: str
    code: str
    marker: str | None  # RUN_BY, NOT_RUN, FILE or None
    detail: str

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}"


def pages() -> list[str]:
    """README.md and every page of docs/, relative to the repository."""
    docs = sorted(p.relative_to(REPO).as_posix() for p in (REPO / "docs").rglob("*.md"))
    return ["README.md", *docs]


def blocks(page: str) -> list[Block]:
    text = (REPO / page).read_text()
    out = []
    for m in _FENCE.finditer(text):
        before = text[:m.start()].rstrip("\n").rsplit("\n", 1)[-1]
        marker = _MARKER.search(before)
        out.append(Block(page, text.count("\n", 0, m.start()) + 1, m.group(1), m.group(2),
                         marker.group(1) if marker else None,
                         marker.group(2).strip() if marker else ""))
    return out


def indented_fences(page: str) -> list[int]:
    """Lines of fences not at the start of a line (inside a list): the parser above skips them."""
    lines = (REPO / page).read_text().splitlines()
    return [i + 1 for i, line in enumerate(lines) if line.lstrip().startswith("```")
            and not line.startswith("```")]


def to_run(page: str) -> list[Block]:
    """The blocks :mod:`tests.docs.test_blocks` runs (files to write included), in page order."""
    return [b for b in blocks(page) if b.marker in (None, FILE) and b.lang not in SHOWN]


def section(page: str, heading: str) -> str:
    """The text of a page from ``heading`` (a whole line) to the next heading of its level."""
    text = (REPO / page).read_text()
    level = heading.split(" ", 1)[0]
    start = text.index(f"\n{heading}\n") + 1
    end = text.find(f"\n{level} ", start + len(heading))
    return text[start:] if end < 0 else text[start:end + 1]


def first_block(text: str, lang: str) -> str:
    """The code of the first ``lang`` block in ``text``."""
    m = re.search(rf"^```{lang}\n(.*?)^```\n", text, re.M | re.S)
    assert m is not None, f"no {lang} block"
    return m.group(1)


def read(page: str) -> str:
    return (REPO / page).read_text()


def path(page: str) -> Path:
    return REPO / page
