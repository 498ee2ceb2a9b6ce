"""osmo's container adapter with real podman and real containers (busybox test images).

Every container and network carries the ``labels`` fixture's label; the fixture fails a
test that leaves one behind.
"""

from __future__ import annotations

import json
import os
import subprocess
import time
import uuid
from pathlib import Path

import pytest

from osmo.runtime.container import (
    DATA_OUTPUT,
    ContainerEngine,
    ContainerError,
    ContainerRun,
    ContainerRuns,
    EngineInfo,
    EngineNotFound,
    Mount,
    data_input,
    detect_engine,
    safe_name,
)
from tests.containers.running import start

ALPINE = "alpine:3.18"


def run_of(labels: dict[str, str], argv: list[str], **kw: object) -> ContainerRun:
    """A run of the busybox image with the test's labels and a fresh name."""
    name = safe_name("test", str(time.monotonic_ns()))
    return ContainerRun(image=ALPINE, name=name, argv=tuple(argv), labels=labels, **kw)  # type: ignore[arg-type]


def inspect(engine: ContainerEngine, name: str) -> str:
    return engine.call("inspect", "--", name)


# ---------------------------------------------------------------- engines


def test_detects_podman_with_its_version(engine: ContainerEngine) -> None:
    assert engine.engine.name == "podman"
    assert engine.engine.version.split(".")[0].isdigit()


def test_no_engine_names_the_package_to_install() -> None:
    with pytest.raises(EngineNotFound) as caught:
        detect_engine(env={"PATH": "/nonexistent"})
    message = str(caught.value)
    assert "podman: not installed" in message and "docker: not installed" in message
    assert "apt-get install podman runc" in message
    assert caught.value.exit_code == 3
    with pytest.raises(EngineNotFound, match="choose podman or docker"):
        detect_engine("lxc")


# ---------------------------------------------------------------- data, env, exit code


def test_mounts_env_output_ownership_and_exit_code(
        runtime: ContainerRuns, images: dict[str, str], labels: dict[str, str],
        tmp_path: Path) -> None:
    inp, out, script = tmp_path / "in", tmp_path / "out", tmp_path / "run.sh"
    inp.mkdir()
    out.mkdir()
    (inp / "data.txt").write_text("from upstream\n")
    script.write_text(f'echo "$GREETING"; cat {data_input(0)}/data.txt\n'
                      f'echo made > {DATA_OUTPUT}/result.txt\n'
                      f'touch {data_input(0)}/x 2>/dev/null || echo "input is read-only" >&2\n'
                      'exit 3\n')
    user = f"{os.getuid()}:{os.getgid()}"
    run = run_of(labels, ["sh", "/tmp/run.sh"], env={"GREETING": "hello 'quoted' $x"},
                 user=user, mounts=(Mount(inp, data_input(0)), Mount(script, "/tmp/run.sh"),
                                    Mount(out, DATA_OUTPUT, read_only=False)))
    started = start(runtime, run, tmp_path)
    assert started.finish() == 3
    assert started.out.decode().splitlines() == ["hello 'quoted' $x", "from upstream"]
    assert started.err.decode() == "input is read-only\n"
    made = out / "result.txt"
    assert made.read_text() == "made\n"
    assert (made.stat().st_uid, made.stat().st_gid) == (os.getuid(), os.getgid())
    assert sorted(p.name for p in inp.iterdir()) == ["data.txt"]


def test_outputs_belong_to_the_user_the_task_runs_as(
        runtime: ContainerRuns, images: dict[str, str], labels: dict[str, str],
        tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir(mode=0o777)
    out.chmod(0o777)
    run = run_of(labels, ["sh", "-c", f"id -u; id -g; echo x > {DATA_OUTPUT}/f"],
                 user="4321:8765", mounts=(Mount(out, DATA_OUTPUT, read_only=False),))
    started = start(runtime, run, tmp_path)
    assert started.finish() == 0
    assert started.out.decode().split() == ["4321", "8765"]
    assert ((out / "f").stat().st_uid, (out / "f").stat().st_gid) == (4321, 8765)


def test_hostile_mount_paths_bind_exactly(
        runtime: ContainerRuns, images: dict[str, str], labels: dict[str, str],
        tmp_path: Path) -> None:
    odd = tmp_path / 'a,b"c:d=e'
    odd.mkdir()
    (odd / "f").write_text("odd\n")
    run = run_of(labels, ["cat", "/in,put:x/f"], mounts=(Mount(odd, "/in,put:x"),))
    started = start(runtime, run, tmp_path)
    assert started.finish() == 0 and started.out == b"odd\n"


def test_a_json_looking_program_is_a_program_name(
        runtime: ContainerRuns, images: dict[str, str], labels: dict[str, str],
        tmp_path: Path) -> None:
    started = start(runtime, run_of(labels, ['["sh","-c","echo injected"]']), tmp_path)
    # not found: 127 from the engine, or 1 from --init's catatonit ("failed to exec pid1")
    assert started.finish() in (1, 127)
    assert b"injected" not in started.out and b"No such file" in started.err


def test_limits_apply(runtime: ContainerRuns, images: dict[str, str], labels: dict[str, str],
                      tmp_path: Path) -> None:
    script = ("cat /sys/fs/cgroup/memory.max 2>/dev/null || "
              "cat /sys/fs/cgroup/memory/memory.limit_in_bytes; "
              "df -k /dev/shm | tail -1")
    run = run_of(labels, ["sh", "-c", script], cpus=0.5, memory=96 << 20, shm_size=64 << 20)
    started = start(runtime, run, tmp_path)
    assert started.finish() == 0, started.err
    lines = started.out.decode().splitlines()
    assert int(lines[0]) == 96 << 20
    assert lines[1].split()[1] == str(64 << 10)


def test_without_a_container_it_runs_a_host_process(runtime: ContainerRuns,
                                                    tmp_path: Path) -> None:
    handle = runtime.start(["sh", "-c", "echo host; exit 4"], cwd=tmp_path,
                           env={"PATH": os.environ["PATH"]})
    from tests.containers.running import Run
    started = Run(runtime, handle)
    assert started.finish() == 4 and started.out == b"host\n"


# ---------------------------------------------------------------- secrets, labels


def test_secret_variables_are_not_in_inspect(
        runtime: ContainerRuns, engine: ContainerEngine, images: dict[str, str],
        labels: dict[str, str], tmp_path: Path) -> None:
    secret = "s3cret-' \"$(rm -rf /)\"-value"
    secret_file = tmp_path / "secret.env"
    run = run_of(labels, ["sh", "-c", 'echo "token=$TOKEN"; echo ready; sleep 60'],
                 env={"PLAIN": "visible"}, secret_env={"TOKEN": secret},
                 secret_env_file=secret_file)
    started = start(runtime, run, tmp_path)
    try:
        started.read_until(b"ready\n")
        assert started.out.decode().splitlines()[0] == f"token={secret}"
        assert secret_file.stat().st_mode & 0o777 == 0o600
        shown = inspect(engine, run.name)
        assert "PLAIN=visible" in shown and labels_of(shown).items() >= labels.items()
        assert "s3cret" not in shown
        cmdline = Path(f"/proc/{started.handle.pid}/cmdline").read_bytes()
        assert b"s3cret" not in cmdline and b"podman" in cmdline
    finally:
        runtime.kill(started.handle, force=True)
        started.finish()
    assert not secret_file.exists()


def labels_of(inspect_json: str) -> dict[str, str]:
    return json.loads(inspect_json)[0]["Config"]["Labels"]


def test_env_file_values_do_show_in_inspect(engine: ContainerEngine, images: dict[str, str],
                                            labels: dict[str, str], tmp_path: Path) -> None:
    """Why secrets take the file route: the engine keeps ``--env-file`` values in inspect."""
    env_file = tmp_path / "env"
    env_file.write_text("TOKEN=envfile-s3cret\n")
    name = safe_name("envfile", str(time.monotonic_ns()))
    engine.call("create", f"--name={name}", f"--label=osmo.test-session={labels['osmo.test-session']}",
                f"--env-file={env_file}", ALPINE, "true")
    try:
        env_file.unlink()  # deleting the file afterwards does not help
        assert "TOKEN=envfile-s3cret" in inspect(engine, name)
    finally:
        assert engine.remove(name)


def test_a_symlink_planted_at_the_secret_file_is_not_followed(
        runtime: ContainerRuns, images: dict[str, str], labels: dict[str, str],
        tmp_path: Path) -> None:
    from osmo.runtime import StartError
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me\n")
    secret_file = tmp_path / "secret.env"
    secret_file.symlink_to(victim)
    run = run_of(labels, ["true"], secret_env={"TOKEN": "s3cret"}, secret_env_file=secret_file)
    with pytest.raises(StartError, match="cannot start container"):
        start(runtime, run, tmp_path)
    assert victim.read_text() == "keep me\n"
    assert not secret_file.is_symlink()


# ---------------------------------------------------------------- networks


def test_group_network_dns_between_two_containers(
        runtime: ContainerRuns, engine: ContainerEngine, images: dict[str, str],
        labels: dict[str, str], tmp_path: Path) -> None:
    network = safe_name("wf", "group", str(time.monotonic_ns()))
    engine.create_network(network, labels)
    engine.create_network(network, labels)  # a retry of the group reuses it
    try:
        server = start(runtime, run_of(
            labels, ["sh", "-c", "echo hello > /tmp/hello.txt; echo listening; "
                                 "nc -w 50 -l -p 24831 < /tmp/hello.txt; echo served"],
            network=network, aliases=("server",), hostname="server"), tmp_path)
        server.read_until(b"listening\n")
        client = start(runtime, run_of(
            labels, ["sh", "-c", "for i in 1 2 3 4 5 6 7 8 9 10; do "
                                 "nc -w 30 server 24831 > /tmp/got && [ -s /tmp/got ] && break; "
                                 "sleep 0.5; done; echo \"Received from server: $(cat /tmp/got)\""],
            network=network, aliases=("client",)), tmp_path)
        assert client.finish() == 0, client.err
        assert client.out.decode().strip() == "Received from server: hello"
        assert server.finish() == 0 and server.out.decode().split() == ["listening", "served"]
        assert engine.networks(labels) == [network]
    finally:
        engine.remove_network(network)
        engine.remove_network(network)  # gone already is fine
    assert engine.networks(labels) == []


# ---------------------------------------------------------------- lifecycle


def test_logs_stream_while_the_container_runs(
        runtime: ContainerRuns, images: dict[str, str], labels: dict[str, str],
        tmp_path: Path) -> None:
    started = start(runtime, run_of(labels, ["sh", "-c", "echo first; echo oops >&2; sleep 60"]),
                    tmp_path)
    started.read_until(b"first\n")
    assert started.handle.popen.poll() is None  # still running: the line came live
    runtime.kill(started.handle, force=True)
    assert started.finish() == 137
    assert started.err.endswith(b"oops\n")


@pytest.mark.parametrize("on_term, code", [("exit 7", 7), (":", 137)],
                         ids=["exits-on-sigterm", "ignores-sigterm"])
def test_kill_sends_sigterm_then_the_forced_kill_ends_it(
        runtime: ContainerRuns, images: dict[str, str], labels: dict[str, str],
        tmp_path: Path, on_term: str, code: int) -> None:
    script = f'trap "echo got TERM; {on_term}" TERM; echo ready; while true; do sleep 0.1; done'
    started = start(runtime, run_of(labels, ["sh", "-c", script]), tmp_path)
    started.read_until(b"ready\n")
    runtime.kill(started.handle)
    started.read_until(b"got TERM\n")
    if code == 137:  # still running after SIGTERM: the pool's grace ends, SIGKILL
        runtime.kill(started.handle, force=True)
    assert started.finish() == code
    assert started.out.decode().splitlines() == ["ready", "got TERM"]


def test_a_kill_right_after_start_stops_the_container(
        runtime: ContainerRuns, images: dict[str, str], labels: dict[str, str],
        tmp_path: Path) -> None:
    """The kill comes while the CLI is still creating the container: it still takes."""
    started = start(runtime, run_of(labels, ["sh", "-c", "echo ran; sleep 300"]), tmp_path)
    runtime.kill(started.handle)
    assert started.finish(timeout=120) == 143  # SIGTERM reached sh, retried until it ran


def test_reaped_while_running_the_container_goes_too(
        runtime: ContainerRuns, images: dict[str, str], labels: dict[str, str],
        tmp_path: Path) -> None:
    """A pool shutting down kills and reaps at once, without waiting for the exit."""
    started = start(runtime, run_of(labels, ["sh", "-c", "echo ready; sleep 300"]), tmp_path)
    started.read_until(b"ready\n")
    runtime.kill(started.handle, force=True)
    assert runtime.reap(started.handle) == 137
    runtime.release(started.handle)


def test_an_unusable_run_is_a_start_error_that_leaves_nothing(
        runtime: ContainerRuns, images: dict[str, str], labels: dict[str, str],
        tmp_path: Path) -> None:
    from osmo.runtime import StartError
    secret_file = tmp_path / "secret.env"
    run = run_of(labels, ["true"], secret_env={"TOKEN": "x"}, secret_env_file=secret_file,
                 mounts=(Mount(tmp_path, "/proc"),))
    with pytest.raises(StartError, match="cannot start container for image 'alpine:3.18': "
                                         "cannot mount over '/proc'"):
        start(runtime, run, tmp_path)
    assert not secret_file.exists()


def test_engine_stop_with_grace(engine: ContainerEngine, images: dict[str, str],
                                labels: dict[str, str]) -> None:
    name = safe_name("stop", str(time.monotonic_ns()))
    label = f"--label=osmo.test-session={labels['osmo.test-session']}"
    engine.call("run", "-d", f"--name={name}", label, ALPINE, "sh", "-c",
                'trap "" TERM; while true; do sleep 0.1; done')
    engine.stop(name, grace=1)
    state = json.loads(inspect(engine, name))[0]["State"]
    assert state["Running"] is False and state["ExitCode"] == 137
    assert engine.remove(name) and not engine.remove(name)


def test_orphans_after_the_cli_is_killed_are_found_and_removed_by_label(
        runtime: ContainerRuns, engine: ContainerEngine, images: dict[str, str],
        labels: dict[str, str], tmp_path: Path) -> None:
    """kill -9 of the worker takes the ``run`` CLI with it; its container runs on."""
    owner = dict(labels, **{"osmo.owner": f"node-{time.monotonic_ns()}"})
    network = safe_name("orphan", str(time.monotonic_ns()))
    engine.create_network(network, owner)
    run = run_of(owner, ["sh", "-c", "echo ready; sleep 300"], network=network)
    started = start(runtime, run, tmp_path)
    started.read_until(b"ready\n")
    os.kill(started.handle.pid, 9)  # the CLI only, as a kill -9 of its parent group would
    started.finish()
    ids = engine.containers(owner)
    assert len(ids) == 1
    assert json.loads(inspect(engine, ids[0]))[0]["State"]["Running"] is True
    assert engine.containers(dict(owner, **{"osmo.owner": "someone-else"})) == []
    removed = engine.remove_labelled(owner)
    assert removed == (ids, [network])
    assert engine.containers(owner) == [] and engine.networks(owner) == []


def test_listing_without_labels_is_refused(engine: ContainerEngine) -> None:
    from osmo.runtime.container import ContainerError
    with pytest.raises(ContainerError, match="label filter"):
        engine.containers({})


# ---------------------------------------------------------------- images


def test_missing_image_pull_failure_says_what_and_why(engine: ContainerEngine,
                                                      podman_env: dict[str, str]) -> None:
    from osmo.runtime.container import ImageError
    lines: list[str] = []
    with pytest.raises(ImageError) as caught:
        engine.resolve("osmo-test-no-such-image:1.0", progress=lines.append)
    message = str(caught.value)
    assert message.startswith("image 'osmo-test-no-such-image:1.0' not found: not on this node "
                              "and the pull failed: ")
    assert "docker.io/library/osmo-test-no-such-image" in "\n".join(lines)
    with pytest.raises(ImageError, match="not on this node .pulling is off."):
        engine.resolve("osmo-test-no-such-image:1.0", pull=False)
    assert caught.value.exit_code == 3


def test_registry_password_never_leaks(engine: ContainerEngine, podman_env: dict[str, str],
                                       tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import tempfile

    from osmo.runtime.container import ImageError, RegistryAuth
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    password = "pw-Zq81-never-shown"
    lines: list[str] = []
    auth = RegistryAuth("registry.osmo-test.invalid", "robot", password)
    with pytest.raises(ImageError) as caught:
        engine.resolve("registry.osmo-test.invalid/team/img:1", progress=lines.append, auth=auth)
    assert "registry.osmo-test.invalid" in str(caught.value)
    assert password not in str(caught.value) and password not in repr(caught.value)
    assert password not in "\n".join(lines)
    assert list(tmp_path.iterdir()) == []  # the private login folder is gone


def test_digest_is_the_image_id_and_follows_a_retag(
        engine: ContainerEngine, images: dict[str, str], podman_env: dict[str, str]) -> None:
    name = f"localhost/osmo-test-digest-{os.getpid()}:1"
    busybox = next(i for n, i in images.items() if n.startswith("localhost/osmo-test/busybox"))
    bash = next(i for n, i in images.items() if n.startswith("localhost/osmo-test/bash"))
    try:
        engine.call("tag", busybox, name)
        first = engine.resolve(name)
        engine.call("tag", bash, name)  # the same tag now names another image
        second = engine.resolve(name)
    finally:
        subprocess.run(["podman", "untag", name, name], capture_output=True, env=podman_env)
    assert first.id == busybox and second.id == bash and first.id != second.id
    assert first.repo_digests and all("@sha256:" in d for d in first.repo_digests)
    assert engine.resolve(ALPINE).id == images[ALPINE]


def test_wait_started_follows_the_event_stream(
        engine: ContainerEngine, runtime: ContainerRuns, images: dict[str, str],
        labels: dict[str, str], tmp_path: Path) -> None:
    """A start before the wait counts (``--since``); a container of another role does not."""
    group = ("osmo.network", f"osmo-test-{uuid.uuid4().hex[:12]}")
    since = time.time()
    peer = start(runtime, run_of({**labels, group[0]: group[1], "osmo.lead": "0"},
                                 ["sh", "-c", "echo up; sleep 300"]), tmp_path)
    peer.read_until(b"up\n")
    lead_before = time.monotonic()
    assert not engine.wait_started(group, ("osmo.lead", "1"), since=since, timeout=2)
    assert time.monotonic() - lead_before >= 2  # waited, found only the peer
    lead = start(runtime, run_of({**labels, group[0]: group[1], "osmo.lead": "1"},
                                 ["sh", "-c", "echo up; sleep 300"]), tmp_path)
    lead.read_until(b"up\n")  # it started before the wait began
    assert engine.wait_started(group, ("osmo.lead", "1"), since=since, timeout=30)
    assert not engine.wait_started(group, ("osmo.lead", "1"), since=time.time() + 1,
                                   timeout=1)  # nothing started after that
    for run in (peer, lead):
        runtime.kill(run.handle, force=True)
        run.finish()


def test_wait_started_without_an_event_stream_is_an_error(
        engine: ContainerEngine, tmp_path: Path) -> None:
    """An engine whose ``events`` ends by itself cannot say: the caller falls back."""
    broken = tmp_path / "podman"
    broken.write_text("#!/bin/sh\necho 'Error: no events here' >&2\nexit 125\n")
    broken.chmod(0o755)
    without = ContainerEngine(EngineInfo("podman", str(broken), engine.engine.version))
    with pytest.raises(ContainerError, match="events"):
        without.wait_started(("osmo.network", "n"), ("osmo.lead", "1"), since=time.time(),
                             timeout=30)
