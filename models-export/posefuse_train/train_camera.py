"""Training the camera network on 2D labels: Gaussian heatmap targets, visibility-weighted MSE,
Adam with step decays, random rotation / scale / flip (with the left-right swap)."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from .budget import StepBudget
from .camera_net import CameraNet
from .config import CameraNetConfig, PipelineConfig
from .keypoints import FLIP
from .losses import heatmap_loss, heatmap_targets


@dataclass
class TrainCameraConfig:
    epochs: float = 12.0
    batch_size: int = 64
    lr: float = 2e-3
    decay_at: tuple[float, ...] = (0.75, 0.92)  # fractions of the run; lr x0.1 at each
    weight_decay: float = 0.0
    rotate_deg: float = 30.0
    rotate_prob: float = 0.5
    scale_range: float = 0.25
    flip_prob: float = 0.5
    sigma_cells: float = 1.0  # target Gaussian sigma in heatmap cells (2 at 64x64 in the paper)
    time_budget_s: float = 0.0  # > 0: stop (with the schedule compressed) when this runs out
    seed: int = 0


def to_input(images_u8: np.ndarray, device) -> torch.Tensor:
    """uint8 [B,S,S,3] -> float [B,3,S,S] in 0..1 (normalized later, after augmentation)."""
    x = torch.from_numpy(np.ascontiguousarray(images_u8)).to(device)
    return x.permute(0, 3, 1, 2).float().div_(255.0)


def normalize(x: torch.Tensor, cfg: PipelineConfig) -> torch.Tensor:
    mean = torch.tensor(cfg.mean, device=x.device).view(1, 3, 1, 1)
    std = torch.tensor(cfg.std, device=x.device).view(1, 3, 1, 1)
    return (x - mean) / std


def augment(x, kp, vis, cfg: TrainCameraConfig, gen: torch.Generator):
    """Random rotation, scale and flip about the crop centre, applied to images [B,3,S,S] (0..1,
    black outside like the server's crop) and keypoints [B,K,2] (model px)."""
    b, _, s, _ = x.shape
    dev = x.device
    u = torch.rand(b, 4, generator=gen).to(dev)
    ang = torch.where(u[:, 0] < cfg.rotate_prob, (u[:, 1] * 2 - 1) * math.radians(cfg.rotate_deg), 0.0)
    scale = 1.0 + (u[:, 2] * 2 - 1) * cfg.scale_range
    flip = u[:, 3] < cfg.flip_prob
    fx = torch.where(flip, -1.0, 1.0)
    c, sn = torch.cos(ang), torch.sin(ang)
    # forward map in normalized coords (centre 0): A = scale * R * diag(fx, 1)
    a = torch.stack([torch.stack([c * fx, -sn], 1), torch.stack([sn * fx, c], 1)], 1) * scale.view(-1, 1, 1)
    inv = torch.linalg.inv(a)
    theta = torch.cat([inv, torch.zeros(b, 2, 1, device=dev)], dim=2)
    grid = F.affine_grid(theta, list(x.shape), align_corners=False)
    x = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    n = kp * (2.0 / s) - 1.0
    n = torch.einsum("bij,bkj->bki", a, n)
    kp = (n + 1.0) * (s / 2.0)
    perm = torch.tensor(FLIP, device=dev)
    kp = torch.where(flip.view(-1, 1, 1), kp[:, perm], kp)
    vis = torch.where(flip.view(-1, 1), vis[:, perm], vis)
    return x, kp, vis


def train_camera(
    data: dict,
    pipeline: PipelineConfig,
    net_cfg: CameraNetConfig,
    cfg: TrainCameraConfig,
    device: str = "cpu",
    log=print,
) -> CameraNet:
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    net = CameraNet(net_cfg).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    m = len(data["image"])
    steps_per_epoch = max(1, m // cfg.batch_size)
    budget = StepBudget(int(round(cfg.epochs * steps_per_epoch)), cfg.time_budget_s, 10)
    h = pipeline.heatmap_size
    rng = np.random.default_rng(cfg.seed)
    net.train()
    t0, step, order, history = time.time(), 0, np.empty(0, np.int64), []
    bar = tqdm(total=budget.total, desc="camera", unit="it", mininterval=5.0)
    ema = None
    while step < budget.total:
        decays = sum(budget.progress(step) >= f for f in cfg.decay_at)
        for g in opt.param_groups:
            g["lr"] = cfg.lr * 0.1**decays
        if len(order) < cfg.batch_size:
            order = np.concatenate([order, rng.permutation(m)])
        idx, order = np.sort(order[: cfg.batch_size]), order[cfg.batch_size :]
        x = to_input(data["image"][idx], device)
        kp = torch.from_numpy(data["kp2d"][idx]).to(device)
        vis = torch.from_numpy(data["kp2d_visible"][idx].astype(np.float32)).to(device)
        x, kp, vis = augment(x, kp, vis, cfg, gen)
        target, weight = heatmap_targets(kp, vis, pipeline.image_size, h, cfg.sigma_cells)
        loss = heatmap_loss(net(normalize(x, pipeline)), target, weight)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        bar.total = budget.update(step)
        history.append(loss.item())
        ema = history[-1] if ema is None else 0.98 * ema + 0.02 * history[-1]
        bar.update(1)
        bar.set_postfix(loss=f"{ema:.2e}", refresh=False)
    bar.close()
    net.loss_history = history
    net.trained_epochs = step * cfg.batch_size / m
    log(
        f"camera: {step} steps ({step * cfg.batch_size / m:.1f} epochs) in {time.time() - t0:.0f}s, "
        f"final loss {ema:.3e}"
    )
    return net.eval()


@torch.no_grad()
def predict_heatmaps(net: CameraNet, images: np.ndarray, pipeline: PipelineConfig, device="cpu", batch=256):
    """Raw (unsmoothed) heatmaps [M,K,H',W'] for uint8 crops [M,S,S,3]."""
    net.eval()
    out = []
    for a in tqdm(range(0, len(images), batch), desc="heatmaps", unit="batch", mininterval=5.0, leave=False):
        x = normalize(to_input(images[a : a + batch], device), pipeline)
        out.append(net(x).float().cpu().numpy())
    return np.concatenate(out, axis=0) if out else np.zeros((0,), np.float32)


def checkpoint(net: CameraNet, pipeline: PipelineConfig, cfg: TrainCameraConfig, data_desc) -> dict:
    return {
        "kind": "camera",
        "config": dataclasses.asdict(net.cfg),
        "state_dict": {k: v.cpu() for k, v in net.state_dict().items()},
        "pipeline": pipeline.to_dict(),
        "train_config": dataclasses.asdict(cfg),
        "data": data_desc,
    }
