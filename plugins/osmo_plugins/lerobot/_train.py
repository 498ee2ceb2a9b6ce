"""The work of ``lerobot.train`` (params in :mod:`osmo_plugins.lerobot.train`).

It trains on every ``lerobot.dataset`` output among its inputs, in input order, as one
dataset: their frames concatenated, their statistics aggregated (LeRobot's
``aggregate_stats``). So shards converted by parallel dataset tasks need no merge; the
datasets must agree on the env, the dimensions, the frame rate and the images.
"""

from __future__ import annotations

import csv
import json
import random
import time
from pathlib import Path
from typing import Any

import numpy as np

from osmo.tasktypes.api import TaskContext
from osmo_plugins._base import find_folders_with, offline
from osmo_plugins.lerobot._dataset import CAMERA, DATASET_MARKER, dataset_root
from osmo_plugins.lerobot.policy_io import POLICY_MARKER
from osmo_plugins.sim.envs import require

__all__ = ["LOSS_TOPIC", "make_config", "run"]

LOSS_TOPIC = "/train/loss"
_LOSS_SCHEMA = {"type": "object", "title": "osmo.TrainLoss", "properties": {
    "step": {"type": "integer"}, "loss": {"type": "number"}, "lr": {"type": "number"},
    "seconds": {"type": "number"}}}


def make_config(p: Any, has_images: bool) -> Any:
    """A small ACT config for CPU: no VAE, no pretrained backbone, re-plan every step."""
    from lerobot.policies.act.configuration_act import ACTConfig

    return ACTConfig(
        chunk_size=p["chunk_size"], n_action_steps=p["n_action_steps"],
        dim_model=p["dim_model"], n_heads=4, dim_feedforward=4 * p["dim_model"],
        n_encoder_layers=1, n_decoder_layers=1, use_vae=False,
        pretrained_backbone_weights=None, vision_backbone="resnet18", device="cpu",
        optimizer_lr=p["lr"], optimizer_lr_backbone=p["lr"], push_to_hub=False,
        dropout=0.0 if not has_images else 0.1)


def _seed(seed: int) -> Any:
    torch = require("torch", "learn")
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    return torch


def run(ctx: TaskContext) -> None:
    """Train and save the policy and its loss curve."""
    p = ctx.params
    offline()
    torch = _seed(p["seed"])
    if p["threads"]:
        torch.set_num_threads(p["threads"])
    from lerobot.datasets import LeRobotDataset, LeRobotDatasetMetadata, resolve_delta_timestamps
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    found, info = _datasets(ctx)
    meta = LeRobotDatasetMetadata(info["repo_id"], root=found[0][0])  # they agree (_SAME)
    cfg = make_config(p, bool(info["images"]))
    policy = make_policy(cfg, ds_meta=meta)
    delta = resolve_delta_timestamps(cfg, meta)
    datasets = [LeRobotDataset(one["repo_id"], root=root, video_backend="pyav",
                               delta_timestamps=delta) for root, one in found]
    pre, post = make_pre_post_processors(cfg, dataset_stats=_stats(datasets))
    loader = _memory_batches(torch, datasets, cfg.chunk_size, p["batch_size"], p["seed"],
                             images=[CAMERA] if info["images"] else [])
    if info["images"]:
        _norms(torch, policy.model.backbone, trainable=True)
    optimizer = torch.optim.AdamW(policy.parameters(), lr=p["lr"], weight_decay=1e-4)
    curve = _train(ctx, torch, policy, pre, loader, optimizer)
    if info["images"]:
        _norms(torch, policy.model.backbone, trainable=False)
    _save(ctx, policy, pre, post, info, curve)


_SAME = ("env", "obs_dim", "action_dim", "padded_action_dim", "fps", "images", "image_size")
"""What the datasets trained on together must agree on."""


def _datasets(ctx: TaskContext) -> tuple[list[tuple[Path, dict[str, Any]]], dict[str, Any]]:
    """Each input dataset's folder and marker, in input order; the markers combined.

    Raises:
        ValueError: no dataset among the inputs, a marker that is no object, has no counts
            or names a root outside its folder, or datasets that disagree on :data:`_SAME`.
    """
    sources = find_folders_with(ctx.inputs, DATASET_MARKER)
    if not sources:
        raise ValueError(f"no {DATASET_MARKER} in the inputs (expected a lerobot.dataset output)")
    found = []
    for source in sources:
        info = json.loads((source / DATASET_MARKER).read_text())
        if not isinstance(info, dict):
            raise ValueError(f"{source / DATASET_MARKER} is not an object")
        counts = [info.get(key) for key in ("episodes", "frames")]
        if not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in counts):
            raise ValueError(f"{source / DATASET_MARKER}: 'episodes' and 'frames' must be "
                             f"counts, not {counts!r}"[:300])
        found.append((dataset_root(source, info), info))
    first = found[0][1]
    for root, info in found[1:]:
        differ = [key for key in _SAME if info.get(key) != first.get(key)]
        if differ:
            raise ValueError(f"the datasets in {found[0][0].parent} and {root.parent} differ "
                             f"in {', '.join(differ)}: they cannot be trained on together")
    combined = {**first, "episodes": sum(info["episodes"] for _, info in found),
                "frames": sum(info["frames"] for _, info in found)}
    return found, combined


def _stats(datasets: list[Any]) -> Any:
    """The normalisation statistics of the datasets as one (LeRobot's own aggregation)."""
    if len(datasets) == 1:
        return datasets[0].meta.stats
    from lerobot.datasets.compute_stats import aggregate_stats

    return aggregate_stats([dataset.meta.stats for dataset in datasets])


def _norms(torch: Any, module: Any, *, trainable: bool) -> None:
    """Swap the backbone's batch norms between LeRobot's frozen kind and trainable ones.

    ACT builds its ResNet with ``FrozenBatchNorm2d``, made for pretrained weights; trained from
    scratch, those are fixed identities and leave an 18-layer net without normalisation, which
    learns slowly. Training real ``BatchNorm2d`` layers and folding their statistics back into
    frozen ones before saving keeps the checkpoint a standard ACT (the same computation in
    eval mode).
    """
    from torchvision.ops.misc import FrozenBatchNorm2d

    for name, child in module.named_children():
        if trainable and isinstance(child, FrozenBatchNorm2d):
            norm = torch.nn.BatchNorm2d(child.weight.shape[0], eps=child.eps)
            with torch.no_grad():
                for key in ("weight", "bias", "running_mean", "running_var"):
                    getattr(norm, key).copy_(getattr(child, key))
            setattr(module, name, norm)
        elif not trainable and isinstance(child, torch.nn.BatchNorm2d):
            frozen = FrozenBatchNorm2d(child.num_features, eps=child.eps)
            for key in ("weight", "bias", "running_mean", "running_var"):
                getattr(frozen, key).copy_(getattr(child, key).detach())
            setattr(module, name, frozen)
        else:
            _norms(torch, child, trainable=trainable)


def _memory_batches(torch: Any, datasets: list[Any], chunk: int, batch_size: int, seed: int,
                    images: list[str]) -> Any:
    """Random batches of the datasets (concatenated, in order) held in memory.

    The same keys, dtypes and padding as LeRobot's ``delta_timestamps`` loader (action chunks
    clamped at the episode's end, with ``action_is_pad``; images as float CHW in [0, 1]),
    about 50× faster than reading frame by frame on this CPU. Frames stay uint8 until a batch
    is drawn (64×64: 12 KB each).
    """
    hfs = [dataset.hf_dataset.with_format("numpy") for dataset in datasets]
    cols = {k: np.concatenate([np.asarray(np.stack(hf[k]), dtype=np.float32) for hf in hfs])
            for k in ("observation.state", "observation.environment_state", "action")}
    frames = {k: torch.from_numpy(np.concatenate([np.stack(list(hf[k])).astype(np.uint8)
                                                  for hf in hfs])) for k in images}
    episodes, offset = [], 0
    for hf in hfs:  # each dataset numbers its episodes from 0: kept apart
        own = np.asarray(hf["episode_index"]).astype(np.int64)
        episodes.append(own + offset)
        offset += int(own.max()) + 1 if len(own) else 0
    episode = np.concatenate(episodes)
    end = np.zeros_like(episode)
    for e in np.unique(episode):
        rows = np.nonzero(episode == e)[0]
        end[rows] = rows.max() + 1
    tensors = {k: torch.from_numpy(v) for k, v in cols.items()}
    gen = torch.Generator().manual_seed(seed)
    offsets = torch.arange(chunk)
    end_t = torch.from_numpy(end)
    while True:
        rows = torch.randint(0, len(episode), (batch_size,), generator=gen)
        idx = rows[:, None] + offsets[None, :]
        pad = idx >= end_t[rows][:, None]
        idx = torch.minimum(idx, end_t[rows][:, None] - 1)
        batch = {"observation.state": tensors["observation.state"][rows],
                 "observation.environment_state":
                     tensors["observation.environment_state"][rows],
                 "action": tensors["action"][idx], "action_is_pad": pad}
        for key, stack in frames.items():
            batch[key] = stack[rows].permute(0, 3, 1, 2).float() / 255.0
        yield batch


def _train(ctx: TaskContext, torch: Any, policy: Any, pre: Any, loader: Any,
           optimizer: Any) -> list[dict[str, float]]:
    p = ctx.params
    policy.train()
    curve: list[dict[str, float]] = []
    schedule = (torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=p["steps"])
                if p["lr_schedule"] == "cosine" else None)
    start, running = time.perf_counter(), 0.0
    for step in range(1, p["steps"] + 1):
        batch = pre(next(loader))
        loss, _ = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), 10.0)
        optimizer.step()
        lr = optimizer.param_groups[0]["lr"]
        if schedule is not None:
            schedule.step()
        running += float(loss.item())
        if step % p["log_every"] == 0 or step == p["steps"]:
            n = step % p["log_every"] or p["log_every"]
            curve.append({"step": step, "loss": running / n, "lr": lr,
                          "seconds": time.perf_counter() - start})
            running = 0.0
            ctx.progress(step, p["steps"], f"loss {curve[-1]['loss']:.4f}")
            ctx.check_cancelled()
    ctx.log.info("trained %d steps in %.1fs (%.3f s/step), final loss %.4f", p["steps"],
                 curve[-1]["seconds"], curve[-1]["seconds"] / p["steps"], curve[-1]["loss"])
    return curve


def _save(ctx: TaskContext, policy: Any, pre: Any, post: Any, info: dict[str, Any],
          curve: list[dict[str, float]]) -> None:
    out = Path(ctx.output)
    ckpt = out / "checkpoint"
    policy.save_pretrained(ckpt)
    pre.save_pretrained(ckpt)
    post.save_pretrained(ckpt)
    marker = {"policy": "act", "env": info["env"], "obs_dim": info["obs_dim"],
              "action_dim": info["action_dim"], "padded_action_dim": info["padded_action_dim"],
              "images": info["images"], "image_size": info.get("image_size"),
              "params": dict(ctx.params),
              "final_loss": curve[-1]["loss"], "dataset_episodes": info["episodes"]}
    (ckpt / POLICY_MARKER).write_text(json.dumps(marker, indent=1) + "\n")
    (out / "loss.json").write_text(json.dumps(curve, indent=1) + "\n")
    with open(out / "loss.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["step", "loss", "lr", "seconds"])
        writer.writeheader()
        writer.writerows(curve)
    with ctx.mcap_writer("loss.mcap") as mcap:
        channel = mcap.add_json_channel(LOSS_TOPIC, "osmo.TrainLoss", _LOSS_SCHEMA)
        for row in curve:  # log time = training seconds, so plots have a real time axis
            mcap.write(channel, row, int(row["seconds"] * 1e9))
