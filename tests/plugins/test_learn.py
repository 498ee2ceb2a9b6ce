"""The learning half in-process: rollouts → LeRobotDataset → ACT training → evaluation."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("numpy")
pytest.importorskip("gymnasium")
pytest.importorskip("lerobot")

from osmo_plugins.lerobot.dataset import DATASET  # noqa: E402
from osmo_plugins.lerobot.train import TRAIN  # noqa: E402
from osmo_plugins.sim.eval import EVAL  # noqa: E402
from osmo_plugins.sim.rollout import ROLLOUT  # noqa: E402

from tests.plugins.fakectx import make_ctx  # noqa: E402


def _shards(tmp: Path, render: bool = False) -> list[Path]:
    outs = []
    for shard in range(2):
        ctx = make_ctx(ROLLOUT, tmp, f"roll{shard}", episodes=2, max_steps=30, noise=0.3,
                       shard=shard, shards=2, render=render, size=32)
        ROLLOUT.run(ctx)
        outs.append(ctx.output)
    return outs


def test_state_only_pipeline(tmp_path: Path) -> None:
    from lerobot.datasets import LeRobotDataset

    ds = make_ctx(DATASET, tmp_path, "dataset", inputs=_shards(tmp_path))
    DATASET.run(ds)
    info = json.loads((ds.output / "osmo_dataset.json").read_text())
    assert (info["episodes"], info["frames"], info["action_dim"]) == (4, 120, 1)
    assert info["padded_action_dim"] == 2 and not info["images"]
    loaded = LeRobotDataset(info["repo_id"], root=ds.output / "dataset", video_backend="pyav")
    assert loaded.num_episodes == 4 and len(loaded) == 120
    assert tuple(loaded[0]["action"].shape) == (2,)

    train = make_ctx(TRAIN, tmp_path, "train", inputs=[ds.output], steps=20, log_every=5)
    TRAIN.run(train)
    curve = json.loads((train.output / "loss.json").read_text())
    assert [row["step"] for row in curve] == [5, 10, 15, 20]
    assert (train.output / "loss.csv").read_text().startswith("step,loss,lr,seconds")
    assert (train.output / "loss.mcap").is_file()
    ckpt = train.output / "checkpoint"
    assert {"config.json", "model.safetensors", "osmo_policy.json"} <= {
        p.name for p in ckpt.iterdir()}

    ev = make_ctx(EVAL, tmp_path, "eval", inputs=[train.output], episodes=2, max_steps=30,
                  policies=["checkpoint", "random"], rrd=False)
    ev.input_named = {"train": train.output}
    EVAL.run(ev)
    rows = json.loads((ev.output / "metrics.json").read_text())["results"]
    assert [r["policy"] for r in rows] == ["train", "random"]
    assert all(0 < r["mean_length"] <= 30 for r in rows)


def test_training_is_seeded(tmp_path: Path) -> None:
    ds = make_ctx(DATASET, tmp_path, "dataset", inputs=_shards(tmp_path))
    DATASET.run(ds)
    losses = []
    for n in range(2):
        train = make_ctx(TRAIN, tmp_path, f"train{n}", inputs=[ds.output], steps=10,
                         log_every=5)
        TRAIN.run(train)
        losses.append([r["loss"] for r in json.loads((train.output / "loss.json").read_text())])
    assert losses[0] == losses[1]


def test_dataset_with_images_trains(tmp_path: Path) -> None:
    ds = make_ctx(DATASET, tmp_path, "dataset", inputs=_shards(tmp_path, render=True))
    DATASET.run(ds)
    info = json.loads((ds.output / "osmo_dataset.json").read_text())
    assert info["images"]
    train = make_ctx(TRAIN, tmp_path, "train", inputs=[ds.output], steps=2, batch_size=4,
                     log_every=1)
    TRAIN.run(train)
    marker = json.loads((train.output / "checkpoint/osmo_policy.json").read_text())
    assert marker["images"] and marker["image_size"] == 32
    ev = make_ctx(EVAL, tmp_path, "eval", inputs=[train.output], episodes=1, max_steps=5,
                  policies=["checkpoint"], rrd=False)
    EVAL.run(ev)  # the env renders 32×32 frames for the policy
    (row,) = json.loads((ev.output / "metrics.json").read_text())["results"]
    assert row["episodes"] == 1 and row["mean_length"] <= 5


def test_dataset_needs_episodes(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="no .mcap episode files"):
        DATASET.run(make_ctx(DATASET, tmp_path, "dataset", inputs=[empty]))


def test_training_refuses_a_dataset_marker_whose_root_leaves_its_folder(tmp_path: Path) -> None:
    """An upstream ``osmo_dataset.json`` names the dataset's folder: only one beside it."""
    ds = make_ctx(DATASET, tmp_path, "dataset", inputs=_shards(tmp_path))
    DATASET.run(ds)
    other = make_ctx(DATASET, tmp_path, "other", inputs=_shards(tmp_path / "o"))
    DATASET.run(other)
    marker = ds.output / "osmo_dataset.json"
    info = json.loads(marker.read_text())
    for n, root in enumerate(("../other/out/dataset", str(other.output / "dataset"), "..", "",
                              None, "missing")):
        marker.write_text(json.dumps({**info, "root": root}))
        with pytest.raises(ValueError, match="'root' must name a folder beside it"):
            TRAIN.run(make_ctx(TRAIN, tmp_path, f"train{n}", inputs=[ds.output], steps=1))


def test_backbone_norms_train_and_fold_back_unchanged() -> None:
    """From scratch the ResNet trains real batch norms; folded back into LeRobot's frozen
    ones, the saved network computes exactly what the trained one does in eval mode."""
    import torch
    import torchvision
    from osmo_plugins.lerobot._train import _norms
    from torchvision.ops.misc import FrozenBatchNorm2d

    torch.manual_seed(0)
    net = torchvision.models.resnet18(weights=None, norm_layer=FrozenBatchNorm2d)
    _norms(torch, net, trainable=True)
    assert not any(isinstance(m, FrozenBatchNorm2d) for m in net.modules())
    net.train()
    net(torch.rand(8, 3, 32, 32) * 3)  # a training step's forward moves the running stats
    net.eval()
    x = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        trained = net(x)
        _norms(torch, net, trainable=False)
        folded = net(x)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules())
    assert torch.allclose(trained, folded, atol=1e-5)


def test_cosine_schedule_decays_the_learning_rate(tmp_path: Path) -> None:
    ds = make_ctx(DATASET, tmp_path, "dataset", inputs=_shards(tmp_path))
    DATASET.run(ds)
    train = make_ctx(TRAIN, tmp_path, "train", inputs=[ds.output], steps=20, log_every=5,
                     lr=0.01, lr_schedule="cosine")
    TRAIN.run(train)
    lrs = [row["lr"] for row in json.loads((train.output / "loss.json").read_text())]
    assert lrs == sorted(lrs, reverse=True) and lrs[0] < 0.01 and lrs[-1] < 0.0002


def test_training_on_shard_datasets_equals_training_on_their_merge(tmp_path: Path) -> None:
    """Two ``lerobot.dataset`` outputs, one per rollout shard, train as the one dataset made
    from both shards: the same frames in the same order and the same statistics (LeRobot's
    aggregation), so the same loss curve; the marker counts every episode."""
    shards = _shards(tmp_path)
    merged = make_ctx(DATASET, tmp_path, "merged", inputs=shards)
    DATASET.run(merged)
    parts = []
    for n, shard in enumerate(shards):
        part = make_ctx(DATASET, tmp_path, f"part{n}", inputs=[shard])
        DATASET.run(part)
        parts.append(part.output)
    curves, markers = [], []
    for name, inputs in (("one", [merged.output]), ("two", parts)):
        train = make_ctx(TRAIN, tmp_path, f"train-{name}", inputs=inputs, steps=10,
                         log_every=5)
        TRAIN.run(train)
        curves.append([r["loss"] for r in json.loads((train.output / "loss.json").read_text())])
        markers.append(json.loads((train.output / "checkpoint/osmo_policy.json").read_text()))
    assert curves[1] == pytest.approx(curves[0], rel=1e-4), curves
    assert markers[0]["dataset_episodes"] == markers[1]["dataset_episodes"] == 4


def test_datasets_that_disagree_are_not_trained_on_together(tmp_path: Path) -> None:
    shards = _shards(tmp_path)
    parts = []
    for n, shard in enumerate(shards):
        part = make_ctx(DATASET, tmp_path, f"part{n}", inputs=[shard])
        DATASET.run(part)
        parts.append(part.output)
    marker = parts[1] / "osmo_dataset.json"
    good = marker.read_text()
    for n, (text, error) in enumerate((
            (good.replace('"obs_dim": 4', '"obs_dim": 5'), "differ in obs_dim"),
            (good.replace('"episodes": 2', '"episodes": "2"'), "must be counts"),
            ("[1, 2]", "is not an object"))):
        marker.write_text(text)
        train = make_ctx(TRAIN, tmp_path, f"train{n}", inputs=parts, steps=2)
        with pytest.raises(ValueError, match=error):
            TRAIN.run(train)
