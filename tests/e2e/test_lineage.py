"""Artifacts and lineage end to end: real server, real files, real MCAP run records."""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from pathlib import Path

from foxglove_schemas_protobuf.Log_pb2 import Log
from mcap.reader import make_reader

from osmo.record import read_run_record
from tests.conftest import Osmo, write

PIPELINE = """
workflow:
  name: three
  tasks:
  - name: raw
    command: [sh, -c, "echo {{value}} > {{output}}/raw.txt; mkdir {{output}}/sub; echo x > {{output}}/sub/x.txt"]
  - name: clean
    command: [sh, -c, "tr a-z A-Z < {{input:raw}}/raw.txt > {{output}}/clean.txt"]
    inputs: [{task: raw}]
  - name: model
    command: [sh, -c, "cat {{input:clean}}/clean.txt {{input:raw}}/raw.txt > {{output}}/model.bin"]
    inputs: [{task: clean}, {task: raw}]
"""


def _run(osmo: Osmo, spec: Path, *args: str) -> str:
    r = osmo("submit", str(spec), "--wait", *args)
    assert r.code == 0, r.out + r.err
    return r.out.splitlines()[0].split(" - ")[1]


def _graph(osmo: Osmo, *args: str) -> dict:
    return json.loads(osmo("lineage", *args, "--format", "json", check=True).out)


def test_lineage_of_a_three_stage_pipeline_both_ways(shared_osmo: Osmo, tmp_path: Path) -> None:
    wf = _run(shared_osmo, write(tmp_path / "p.yaml", PIPELINE), "--set", "value=abc")
    up = _graph(shared_osmo, f"{wf}:model")
    tasks = {n["task"] for n in up["nodes"].values()}
    assert tasks == {"raw", "clean", "model"}
    by_task = {n["task"]: key for key, n in up["nodes"].items()}
    assert sorted(map(tuple, up["edges"])) == sorted([
        (by_task["raw"], by_task["clean"]), (by_task["clean"], by_task["model"]),
        (by_task["raw"], by_task["model"])])
    model = up["nodes"][by_task["model"]]
    assert model["workflow_id"] == wf and model["exit_code"] == 0
    assert {i["task"] for i in model["inputs"]} == {"clean", "raw"}
    assert model["command"][:2] == ["sh", "-c"]
    assert "{{" not in " ".join(model["command"])  # the argv that ran, tokens resolved
    assert "/clean/" in model["command"][2] and "/raw/" in model["command"][2]

    down = _graph(shared_osmo, f"{wf}:raw", "--downstream")
    assert {n["task"] for n in down["nodes"].values()} == {"raw", "clean", "model"}
    text = shared_osmo("lineage", f"{wf}:model", check=True).out
    assert text.splitlines()[0].startswith(f"model [{wf}]") and "(see above)" in text


def test_artifacts_list_get_and_lineage_of_a_local_file(shared_osmo: Osmo, tmp_path: Path) -> None:
    wf = _run(shared_osmo, write(tmp_path / "p.yaml", PIPELINE), "--set", "value=xyz")
    listed = json.loads(shared_osmo("artifacts", "list", wf, "raw", "--format", "json",
                                    check=True).out)
    assert [f["path"] for f in listed[0]["files"]] == ["raw.txt", "sub/x.txt"]
    dest = tmp_path / "fetched"
    shared_osmo("artifacts", "get", f"{wf}:clean", "-o", str(dest), check=True)
    assert (dest / "clean.txt").read_text() == "XYZ\n"
    graph = _graph(shared_osmo, str(dest / "clean.txt"))  # a file found by its digest
    assert {n["task"] for n in graph["nodes"].values()} == {"raw", "clean"}
    assert graph["blob"] is not None


def test_outputs_are_deduplicated_and_gc_keeps_referenced_blobs(osmo: Osmo,
                                                                 tmp_path: Path) -> None:
    spec = write(tmp_path / "p.yaml", PIPELINE)
    first, second = _run(osmo, spec, "--set", "value=same"), _run(osmo, spec, "--set", "value=same")
    a = json.loads(osmo("artifacts", "list", first, "model", "--format", "json").out)[0]
    b = json.loads(osmo("artifacts", "list", second, "model", "--format", "json").out)[0]
    assert a["manifest"] == b["manifest"]  # identical outputs: one manifest, shared blobs
    blobs = list((osmo.home / "artifacts" / "blobs").rglob("*"))
    stray = osmo.home / "artifacts" / "blobs" / "sha256" / "00" / ("0" * 62)
    stray.parent.mkdir(parents=True, exist_ok=True)
    stray.write_text("unreferenced")
    old = time.time() - 3 * 86400
    os.utime(stray, (old, old))
    assert "removed" in osmo("artifacts", "gc", check=True).out
    assert all(p.exists() for p in blobs)  # everything referenced survives
    dest = tmp_path / "again"
    osmo("artifacts", "get", f"{second}:model", "-o", str(dest), check=True)
    assert (dest / "model.bin").read_text() == "SAME\nsame\n"


def test_corrupted_blob_is_reported_not_used(osmo: Osmo, tmp_path: Path) -> None:
    wf = _run(osmo, write(tmp_path / "p.yaml", PIPELINE), "--set", "value=good")
    entry = json.loads(osmo("artifacts", "list", wf, "clean", "--format", "json").out)[0]
    digest = entry["files"][0]["digest"]
    blob = osmo.home / "artifacts" / "blobs" / "sha256" / digest[7:9] / digest[9:]
    blob.chmod(0o644)
    blob.write_text("EVIL\n")
    r = osmo("artifacts", "get", digest, "-o", str(tmp_path / "out"))
    assert r.code == 3 and digest in r.err and "Traceback" not in r.err
    assert not (tmp_path / "out" / "clean.txt").exists()


def test_run_record_is_an_mcap_with_status_lineage_and_logs(shared_osmo: Osmo,
                                                            tmp_path: Path) -> None:
    wf = _run(shared_osmo, write(tmp_path / "p.yaml", PIPELINE), "--set", "value=rec")
    record = shared_osmo.home / "runs" / wf / "run.mcap"
    deadline = time.monotonic() + 60
    while not record.exists():  # written just after the workflow's end is committed
        assert time.monotonic() < deadline, "run record never written"
        time.sleep(0.05)
    with open(record, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        channels = {c.topic: c for c in summary.channels.values()}
        assert {"/osmo/status", "/osmo/lineage", "/osmo/log"} == set(channels)
        schemas = {s.id: s for s in summary.schemas.values()}
        assert schemas[channels["/osmo/status"].schema_id].encoding == "jsonschema"
        assert schemas[channels["/osmo/lineage"].schema_id].encoding == "jsonschema"
        log_schema = schemas[channels["/osmo/log"].schema_id]
        assert (log_schema.name, log_schema.encoding) == ("foxglove.Log", "protobuf")
        by_topic: dict[str, list] = {}
        for _schema, channel, message in reader.iter_messages():
            value = (Log.FromString(message.data) if channel.topic == "/osmo/log"
                     else json.loads(message.data))
            by_topic.setdefault(channel.topic, []).append(value)
    assert {m["task"] for m in by_topic["/osmo/lineage"]} == {"raw", "clean", "model"}
    assert by_topic["/osmo/status"][-1]["status"] == "COMPLETED"
    assert any(m["task"] is None for m in by_topic["/osmo/status"])
    assert by_topic["/osmo/log"][-1].message.startswith("workflow COMPLETED")
    assert {m.name for m in by_topic["/osmo/log"]} >= {"raw", "clean", "model", wf}
    assert read_run_record(record)["status"][-1]["status"] == "COMPLETED"


def test_mcap_written_by_a_task_carries_its_lineage_away(osmo: Osmo, tmp_path: Path) -> None:
    spec = write(tmp_path / "m.yaml", """
workflow:
  name: robot
  tasks:
  - name: rollout
    command: ["{{py}}", /tmp/rollout.py, "{{output}}/episode.mcap"]
    files:
    - path: /tmp/rollout.py
      contents: |
        import sys
        from osmo.record import Lineage, LineageMcapWriter
        with LineageMcapWriter(sys.argv[1], Lineage.from_env()) as w:
            ch = w.add_json_channel("/joint", "Joint", {"type": "object"})
            for i in range(5):
                w.write(ch, {"q": i * 0.1})
        print("wrote episode")
""")
    wf = _run(osmo, spec, "--set-string", f"py={sys.executable}")
    dest = tmp_path / "carried"
    osmo("artifacts", "get", f"{wf}:rollout", "-o", str(dest), check=True)
    carried = tmp_path / "elsewhere.mcap"
    shutil.copy(dest / "episode.mcap", carried)
    osmo.stop_server()
    shutil.rmtree(osmo.home)  # no store, no server: the file alone says where it came from
    r = osmo("lineage", str(carried), "--format", "json")
    assert r.code == 0, r.err
    node = next(iter(json.loads(r.out)["nodes"].values()))
    assert node["workflow_id"] == wf and node["task"] == "rollout" and node["retry"] == 0
