"""Training the point network on pseudo labels: per-epoch random subsampling to N points, random
rotation about the vertical axis (points and labels together), camera features from the frozen
camera net's smoothed heatmaps sampled exactly as the server does, L = L_reg + lambda * L_seg,
SGD with momentum and cosine decay."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from .budget import StepBudget
from .config import PipelineConfig, PointNetConfig
from .fusion import sample_features
from .keypoints import K
from .labels import segmentation_labels
from .losses import regression_loss, segmentation_loss
from .point_net import PointNet


@dataclass
class TrainPointConfig:
    fusion: bool = True
    seg: bool = True
    epochs: float = 30.0
    steps: int = 0  # > 0: exactly this many steps (overrides epochs)
    batch_size: int = 128
    optimizer: str = "sgd"  # "sgd" (paper) or "adam"
    lr: float = 0.05
    momentum: float = 0.9
    weight_decay: float = 1e-4
    warmup_steps: int = 50
    seg_weight: float = 0.1  # lambda
    seg_radius: float = 0.05  # positive radius r, in units of S
    w_pos: float = 20.0
    w_neg: float = 1.0
    # Uniform in [-x, x] about z. The paper rotates by [0, 2 pi); here points are already in the
    # heading-aligned box frame, and a full turn would throw the heading (and with it the
    # left/right cue) away: on a pilot set 180 gave 39.8% OKS@3D against 62.3% for 20.
    rotate_deg: float = 20.0
    time_budget_s: float = 0.0  # > 0: stop (with the schedule compressed) when this runs out
    seed: int = 0


def select_points(counts: torch.Tensor, n: int, p: int, gen: torch.Generator) -> torch.Tensor:
    """[B] counts -> [B,N] indices: a random subset without replacement when count >= N, otherwise
    every point once and random repeats (like the server's selection, but fresh every epoch)."""
    b = len(counts)
    keys = torch.rand(b, p, generator=gen)
    keys[torch.arange(p).unsqueeze(0) >= counts.unsqueeze(1)] = -1.0
    idx = keys.argsort(dim=1, descending=True)[:, :n]
    if idx.shape[1] < n:
        idx = torch.cat([idx, torch.zeros(b, n - idx.shape[1], dtype=idx.dtype)], dim=1)
    rep = (torch.rand(b, n, generator=gen) * counts.clamp(min=1).unsqueeze(1)).long()
    short = torch.arange(n).unsqueeze(0) >= counts.unsqueeze(1)
    return torch.where(short, rep, idx)


def rotate_z(x: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotates [B,*,3] about the vertical axis by angle [B]."""
    c, s = torch.cos(angle).view(-1, 1), torch.sin(angle).view(-1, 1)
    return torch.stack([c * x[..., 0] - s * x[..., 1], s * x[..., 0] + c * x[..., 1], x[..., 2]], dim=-1)


def point_batch(xyz, uv, smoothed, image_size: int):
    """Network input [B,N,3(+K)] from xyz [B,N,3], uv [B,N,2] and smoothed heatmaps (or None)."""
    if smoothed is None:
        return xyz
    return torch.cat([xyz, sample_features(smoothed, uv, image_size)], dim=2)


def train_point(
    data: dict,
    labels: dict,
    smoothed: np.ndarray | None,
    pipeline: PipelineConfig,
    net_cfg: PointNetConfig,
    cfg: TrainPointConfig,
    device: str = "cpu",
    desc: str = "point",
    log=print,
) -> PointNet:
    """data: shard arrays; labels: pseudo_labels(); smoothed: [M,K,H,W] camera heatmaps after
    smoothing (fusion only)."""
    if cfg.fusion != (smoothed is not None) or net_cfg.in_features != (3 + K if cfg.fusion else 3):
        raise ValueError("fusion needs smoothed heatmaps and 3+K input features; LiDAR-only neither")
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    counts_np = data["points_count"]
    usable = np.flatnonzero((counts_np > 0) & (labels["weight"] > 0).any(axis=1))
    m = len(usable)
    if m == 0:
        raise ValueError("no training sample has points and a pseudo label")
    xyz_all = torch.from_numpy(data["points_xyz"])
    uv_all = torch.from_numpy(data["points_uv"])
    counts = torch.from_numpy(counts_np.astype(np.int64))
    kp3d = torch.from_numpy(labels["kp3d"])
    weight = torch.from_numpy(labels["weight"])
    vis = torch.from_numpy(labels["visible"].astype(np.float32))
    kp2d = torch.from_numpy(data["kp2d"])
    sm = None if smoothed is None else torch.from_numpy(smoothed)
    n, p, s = pipeline.num_points, xyz_all.shape[1], pipeline.image_size

    net = PointNet(net_cfg).to(device)
    if cfg.optimizer == "adam":
        opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    else:
        opt = torch.optim.SGD(
            net.parameters(), lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay, nesterov=True
        )
    steps_per_epoch = max(1, m // cfg.batch_size)
    max_steps = cfg.steps if cfg.steps > 0 else int(round(cfg.epochs * steps_per_epoch))
    budget = StepBudget(max_steps, cfg.time_budget_s, 2 * cfg.warmup_steps)

    def lr_at(step):
        if step < cfg.warmup_steps:
            return cfg.lr * (step + 1) / cfg.warmup_steps
        t = (step - cfg.warmup_steps) / max(1, budget.total - cfg.warmup_steps)
        return cfg.lr * 0.5 * (1 + math.cos(math.pi * min(1.0, t)))

    rng = np.random.default_rng(cfg.seed)
    net.train()
    t0, step, order, ema, history = time.time(), 0, np.empty(0, np.int64), None, []
    bar = tqdm(total=budget.total, desc=desc, unit="it", mininterval=5.0)
    while step < budget.total:
        for g in opt.param_groups:
            g["lr"] = lr_at(step)
        if len(order) < cfg.batch_size:
            order = np.concatenate([order, rng.permutation(usable)])
        idx, order = torch.from_numpy(order[: cfg.batch_size]), order[cfg.batch_size :]
        sel = select_points(counts[idx], n, p, gen)
        xyz = torch.gather(xyz_all[idx], 1, sel.unsqueeze(2).expand(-1, -1, 3))
        uv = torch.gather(uv_all[idx], 1, sel.unsqueeze(2).expand(-1, -1, 2))
        target = kp3d[idx]
        if cfg.rotate_deg > 0:
            ang = (torch.rand(len(idx), generator=gen) * 2 - 1) * math.radians(cfg.rotate_deg)
            xyz, target = rotate_z(xyz, ang), rotate_z(target, ang)
        x = point_batch(xyz, uv, None if sm is None else sm[idx], s).to(device)
        pred, seg_logits = net(x)
        loss = regression_loss(pred, target.to(device), weight[idx].to(device))
        if cfg.seg:
            seg_lab = segmentation_labels(kp2d[idx], vis[idx], uv, s, cfg.seg_radius).to(device)
            loss = loss + cfg.seg_weight * segmentation_loss(
                seg_logits, seg_lab, vis[idx].to(device), cfg.w_pos, cfg.w_neg
            )
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        bar.total = budget.update(step)
        history.append(loss.item())
        ema = history[-1] if ema is None else 0.98 * ema + 0.02 * history[-1]
        bar.update(1)
        bar.set_postfix(loss=f"{ema:.3f}", refresh=False)
    bar.close()
    net.loss_history = history
    net.trained_epochs = step * cfg.batch_size / m
    log(
        f"{desc}: {step} steps ({step * cfg.batch_size / m:.1f} epochs) on {m} samples "
        f"in {time.time() - t0:.0f}s, final loss {ema:.4f}"
    )
    return net.eval()


@torch.no_grad()
def predict_points(net: PointNet, xyz: np.ndarray, uv: np.ndarray, smoothed, image_size: int, batch=512):
    """Keypoints [M,K,3] for the serve points xyz [M,N,3] / uv [M,N,2]."""
    net.eval()
    out = []
    for a in range(0, len(xyz), batch):
        sm = None if smoothed is None else torch.from_numpy(smoothed[a : a + batch])
        x = point_batch(
            torch.from_numpy(xyz[a : a + batch]), torch.from_numpy(uv[a : a + batch]), sm, image_size
        )
        out.append(net(x)[0].numpy())
    return np.concatenate(out, axis=0) if out else np.zeros((0, K, 3), np.float32)


def checkpoint(net: PointNet, pipeline: PipelineConfig, cfg: TrainPointConfig, data_desc) -> dict:
    return {
        "kind": "point",
        "config": dataclasses.asdict(net.cfg),
        "state_dict": {k: v.cpu() for k, v in net.state_dict().items()},
        "pipeline": pipeline.to_dict(),
        "train_config": dataclasses.asdict(cfg),
        "data": data_desc,
    }
