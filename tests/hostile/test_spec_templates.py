"""Hostile templates: memory and time bombs are rendered in a child under limits.

A five-line template can ask Jinja for gigabytes or hold the GIL for minutes. Each one must
fail with exit 2 naming the limit, in the CLI's process (``osmo validate``) and in the
server's (``osmo submit`` to a local server), and the server must answer other clients while
one renders.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest

from osmo.errors import InfrastructureError, SpecError
from osmo.spec import isolation, load_spec, render_spec
from osmo.spec import template as template_module
from tests.conftest import REPO, Osmo, write

HEAD = "workflow:\n  name: bomb\n  tasks:\n  - name: a\n    command: [echo]\n"

MEMORY_BOMBS = {
    "join": "{% set x = 'x' * 10000000 %}{{ ([x] * 80) | join }}",
    "doubling": ("{% set ns = namespace(s='x') %}{% for i in range(40) %}"
                 "{% set ns.s = ns.s ~ ns.s %}{% endfor %}{{ ns.s | length }}"),
    "format-width": "{{ '%1500000000d' | format(1) }}",
    "center-folded": "{{ 'x' | center(1500000000) }}",
}
TIME_BOMBS = {
    "big-power": "{{ ((10 ** 1000) ** 1000) ** 100 }}",  # holds the GIL, ~40 MB
    "bigger-power": "{{ ((10 ** 1000) ** 1000) ** 1000 }}",
    "string-loop": ("{% for c in 'x' * 10000000 %}{% for d in 'x' * 10000000 %}"
                    "{% endfor %}{% endfor %}"),
    "lipsum": "{{ lipsum(n=10**8) | length }}",
}


def _spec(bomb: str) -> str:
    return HEAD + f'    args: ["{bomb}"]\n'


def _maxrss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


@pytest.fixture
def short_time(monkeypatch: pytest.MonkeyPatch) -> None:
    """A 2 s time limit, so a time bomb costs this suite 2 s and not 10."""
    monkeypatch.setattr(isolation, "MAX_SECONDS", 2.0)


@pytest.mark.parametrize("name", sorted(MEMORY_BOMBS))
def test_memory_bomb_stops_at_the_memory_limit(name: str, short_time: None) -> None:
    before = _maxrss_mib()
    with pytest.raises(SpecError) as info:
        render_spec(text=MEMORY_BOMBS[name], filename="bomb.yaml")
    message = str(info.value)
    assert message.startswith("bomb.yaml"), message
    assert "memory limit" in message and f"{isolation.MAX_MEMORY // 2**20} MiB" in message
    assert _maxrss_mib() - before < 100  # this process never held the bomb


@pytest.mark.parametrize("name", sorted(TIME_BOMBS))
def test_time_bomb_stops_at_the_time_limit(name: str, short_time: None) -> None:
    t0 = time.monotonic()
    with pytest.raises(SpecError) as info:
        load_spec(text=_spec(TIME_BOMBS[name]), filename="bomb.yaml")
    message = str(info.value)
    assert ("time limit" in message and "2 s" in message) or "memory limit" in message, message
    assert time.monotonic() - t0 < 2.0 + 8.0  # the limit plus slack for a loaded machine


def test_ordinary_templates_render_as_before() -> None:
    text = ("default-values: {n: 2, when: 2024-01-02}\nworkflow:\n  name: ok-{{ n }}\n"
            "  tasks:\n{% for i in range(n) %}  - {name: t{{ i }}, command: [echo, "
            "'{{ when.year }}', '{{output}}']}\n{% endfor %}")
    spec = load_spec(text=text, set_values=["n=3"])
    assert [t.name for t in spec.all_tasks()] == ["t0", "t1", "t2"]
    assert spec.task("t0").command == ("echo", "2024", "{{output}}")


@pytest.mark.parametrize("text", [
    "a: 1\r\nb: '{{output}}'\rc: 3\n",
    "plain: text\n\n",
    "x: {{output}}\n",
    "",
])
def test_files_without_jinja_render_as_jinja_would(text: str) -> None:
    assert not isolation.needs_jinja(text)
    assert isolation.render(text, "f.yaml") == template_module.render(text, "f.yaml", {})


def test_jinja_syntax_is_detected_outside_special_tokens() -> None:
    assert isolation.needs_jinja("a: {{ x }}")
    assert isolation.needs_jinja("{% if 1 %}{% endif %}")
    assert isolation.needs_jinja("{# note #}")
    assert not isolation.needs_jinja("a: '{{ output }}/{{input:0}}/{{host:b}}'")


def test_bad_set_items_are_reported_without_jinja() -> None:
    with pytest.raises(SpecError, match="--set 'oops': expected NAME=VALUE"):
        load_spec(text=HEAD, set_values=["oops"])


def test_cli_validate_stops_a_bomb_in_its_own_process(tmp_path: Path) -> None:
    spec = write(tmp_path / "bomb.yaml", _spec(MEMORY_BOMBS["center-folded"]))
    proc = subprocess.run([sys.executable, "-m", "osmo", "validate", str(spec)],
                          capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 2, proc.stderr
    assert "memory limit" in proc.stderr and "Traceback" not in proc.stderr


def _render_children(server_pid: int) -> list[int]:
    """Pids of processes whose grandparent is the server (the renderer's children)."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            parents[int(entry.name)] = int(stat.rsplit(")", 1)[1].split()[1])
    helpers = {pid for pid, ppid in parents.items() if ppid == server_pid}
    return [pid for pid, ppid in parents.items() if ppid in helpers]


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_the_server_never_renders_a_clients_template(osmo: Osmo, tmp_path: Path) -> None:
    """A template bomb is the client's own problem: the client renders (under the same time
    limit) and the server, which renders no client's file since issue 13, does no work for it
    and keeps answering."""
    osmo("server", "start", check=True)
    pid = osmo.server_pid()
    assert pid is not None
    cpu = _cpu_seconds(pid)
    spec = write(tmp_path / "slow.yaml", _spec(TIME_BOMBS["big-power"]))
    submit = subprocess.Popen([sys.executable, "-m", "osmo", "submit", str(spec)],
                              env=osmo.env, cwd=REPO, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    try:
        out, err = submit.communicate(timeout=120)
    finally:
        if submit.poll() is None:
            submit.kill()
    assert submit.returncode == 2, (out, err)
    assert "time limit" in err and f"{isolation.MAX_SECONDS:g} s" in err
    assert "Traceback" not in err
    assert not _render_children(pid) and _cpu_seconds(pid) < cpu + 1.0
    assert osmo.server_pid() == pid and osmo("list", "--format", "json", check=True).json() == []


def test_server_survives_a_memory_bomb(osmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "big.yaml", _spec(MEMORY_BOMBS["join"]))
    result = osmo("submit", str(spec))
    assert result.code == 2 and "memory limit" in result.err, result
    pid = osmo.server_pid()
    assert pid is not None and osmo("list", check=True).code == 0
    assert osmo.server_pid() == pid
    status = Path(f"/proc/{pid}/status").read_text()
    rss_kib = int(next(ln for ln in status.splitlines() if ln.startswith("VmHWM")).split()[1])
    assert rss_kib < 400 * 1024  # the server itself never held the 800 MB string
    assert os.path.exists(f"/proc/{pid}")


def test_a_killed_renderer_is_started_again() -> None:
    assert render_spec(text="a: {{ 1 + 1 }}\n") == "a: 2\n"
    helper = isolation._HELPER._proc
    assert helper is not None
    helper.kill()  # the helper this process started
    helper.wait()
    assert render_spec(text="a: {{ 2 + 2 }}\n") == "a: 4\n"


def test_a_renderer_that_cannot_start_is_an_infrastructure_error(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(isolation.sys, "executable", str(tmp_path / "no-python"))
    helper = isolation._Helper()  # a fresh one: this process's own helper stays as it is
    with pytest.raises(InfrastructureError, match="cannot reach the template renderer"):
        helper.render({"text": "{{ 1 }}", "file": "f", "set_values": [], "set_strings": [],
                       "seconds": 1.0, "memory": isolation.MAX_MEMORY})
