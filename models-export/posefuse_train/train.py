"""Training both networks with one loop, `fit`.

Camera network: Gaussian heatmap targets from the 2D labels, visibility-weighted MSE, Adam with
step decays, random rotation / scale / flip (with the left-right swap).

Point network: pseudo 3D labels (labels.py), per-epoch random subsampling to N points, random
rotation about the vertical axis (points and labels together), camera features from the frozen
camera net's smoothed heatmaps sampled exactly as the server does, L = L_reg + lambda * L_seg,
SGD with Nesterov momentum, warm-up and cosine decay.

A run's length is a number of steps fixed by the configuration (epochs, or steps), so the same
command and seed give the same weights. A wall-clock budget (`time_budget_s`) is opt-in: it
shortens the run (and compresses the schedule) to what fits, which depends on the machine.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from .camera_net import CameraNet
from .config import CameraNetConfig, PipelineConfig, PointNetConfig
from .fusion import sample_features
from .keypoints import FLIP, K
from .labels import segmentation_labels
from .losses import heatmap_loss, heatmap_targets, regression_loss, segmentation_loss
from .point_net import PointNet

# --- the loop ----------------------------------------------------------------------------------


class StepBudget:
    """The number of steps of a run: `max_steps`, or with `seconds` > 0 as many as fit in that
    wall-clock time (re-estimated from the measured step rate as training goes, at least
    `min_steps`)."""

    def __init__(self, max_steps: int, seconds: float = 0.0, min_steps: int = 1, clock=time.monotonic):
        self.max_steps = max(1, max_steps)
        self.seconds = seconds
        self.min_steps = min_steps
        self.total = self.max_steps
        self.clock = clock
        self.t0 = clock()

    def update(self, step: int) -> int:
        """Call after `step` steps are done; returns the current total."""
        if self.seconds > 0 and step > 0 and (step in (3, 10, 30) or step % 50 == 0):
            rate = max(self.clock() - self.t0, 1e-9) / step
            fit = int(self.seconds / rate)
            self.total = max(min(self.min_steps, self.max_steps), step + 1, min(self.max_steps, fit))
        return self.total


def fit(
    net: torch.nn.Module,
    opt: torch.optim.Optimizer,
    batch_loss,
    lr_at,
    steps: int,
    *,
    time_budget_s: float = 0.0,
    min_steps: int = 1,
    desc: str = "train",
    clock=time.monotonic,
) -> list[float]:
    """The training loop of both networks: `steps` optimizer steps on `batch_loss(step)` (a scalar
    tensor), the learning rate of each step from `lr_at(step, total_steps)`. With `time_budget_s`
    > 0 the run stops early when the budget runs out (see StepBudget). Returns the loss per step
    and leaves the network in eval mode."""
    budget = StepBudget(steps, time_budget_s, min_steps, clock)
    net.train()
    step, ema, history = 0, None, []
    bar = tqdm(total=budget.total, desc=desc, unit="it", mininterval=5.0)
    while step < budget.total:
        for g in opt.param_groups:
            g["lr"] = lr_at(step, budget.total)
        loss = batch_loss(step)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        bar.total = budget.update(step)
        history.append(loss.item())
        ema = history[-1] if ema is None else 0.98 * ema + 0.02 * history[-1]
        bar.update(1)
        bar.set_postfix(loss=f"{ema:.3e}", refresh=False)
    bar.close()
    net.eval()
    return history


def batches(rng: np.random.Generator, indices: np.ndarray, batch_size: int):
    """Endless batches of `indices`: a fresh permutation each epoch, carried across epochs."""
    order = np.empty(0, np.int64)
    while True:
        if len(order) < batch_size:
            order = np.concatenate([order, rng.permutation(indices)])
        yield order[:batch_size]
        order = order[batch_size:]


def seed_everything(seed: int) -> tuple[torch.Generator, np.random.Generator]:
    """Seeds torch (initialisation) and returns the generators of augmentation and sampling."""
    torch.manual_seed(seed)
    if torch.cuda.is_available():
        torch.backends.cudnn.deterministic = True
        torch.backends.cudnn.benchmark = False
    return torch.Generator().manual_seed(seed), np.random.default_rng(seed)


# --- camera network ----------------------------------------------------------------------------


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
    time_budget_s: float = 0.0  # opt-in: > 0 stops (with the schedule compressed) when this runs out
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
    gen, rng = seed_everything(cfg.seed)
    net = CameraNet(net_cfg).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    m = len(data["image"])
    steps = int(round(cfg.epochs * max(1, m // cfg.batch_size)))
    order = batches(rng, np.arange(m), cfg.batch_size)

    def lr_at(step, total):
        return cfg.lr * 0.1 ** sum(step / total >= f for f in cfg.decay_at)

    def batch_loss(_step):
        idx = np.sort(next(order))
        x = to_input(data["image"][idx], device)
        kp = torch.from_numpy(data["kp2d"][idx]).to(device)
        vis = torch.from_numpy(data["kp2d_visible"][idx].astype(np.float32)).to(device)
        x, kp, vis = augment(x, kp, vis, cfg, gen)
        target, weight = heatmap_targets(kp, vis, pipeline.image_size, pipeline.heatmap_size, cfg.sigma_cells)
        return heatmap_loss(net(normalize(x, pipeline)), target, weight)

    t0 = time.time()
    history = fit(
        net, opt, batch_loss, lr_at, steps, time_budget_s=cfg.time_budget_s, min_steps=10, desc="camera"
    )
    net.loss_history = history
    net.trained_epochs = len(history) * cfg.batch_size / m
    log(
        f"camera: {len(history)} steps ({net.trained_epochs:.1f} epochs) in {time.time() - t0:.0f}s, "
        f"final loss {np.mean(history[-50:]):.3e}"
    )
    return net


@torch.no_grad()
def predict_heatmaps(net: CameraNet, images: np.ndarray, pipeline: PipelineConfig, device="cpu", batch=256):
    """Raw (unsmoothed) heatmaps [M,K,H',W'] for uint8 crops [M,S,S,3]."""
    net.eval()
    out = []
    for a in tqdm(range(0, len(images), batch), desc="heatmaps", unit="batch", mininterval=5.0, leave=False):
        x = normalize(to_input(images[a : a + batch], device), pipeline)
        out.append(net(x).float().cpu().numpy())
    return np.concatenate(out, axis=0) if out else np.zeros((0,), np.float32)


# --- point network -----------------------------------------------------------------------------


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
    # Uniform in [-x, x] about z (the paper: [0, 2 pi)); docs/results-choices.md says why 20 by default.
    rotate_deg: float = 20.0
    time_budget_s: float = 0.0  # opt-in: > 0 stops (with the schedule compressed) when this runs out
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
    gen, rng = seed_everything(cfg.seed)
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
    steps = cfg.steps if cfg.steps > 0 else int(round(cfg.epochs * max(1, m // cfg.batch_size)))
    order = batches(rng, usable, cfg.batch_size)

    def lr_at(step, total):
        if step < cfg.warmup_steps:
            return cfg.lr * (step + 1) / cfg.warmup_steps
        t = (step - cfg.warmup_steps) / max(1, total - cfg.warmup_steps)
        return cfg.lr * 0.5 * (1 + math.cos(math.pi * min(1.0, t)))

    def batch_loss(_step):
        idx = torch.from_numpy(next(order))
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
        return loss

    t0 = time.time()
    history = fit(
        net,
        opt,
        batch_loss,
        lr_at,
        steps,
        time_budget_s=cfg.time_budget_s,
        min_steps=2 * cfg.warmup_steps,
        desc=desc,
    )
    net.loss_history = history
    net.trained_epochs = len(history) * cfg.batch_size / m
    log(
        f"{desc}: {len(history)} steps ({net.trained_epochs:.1f} epochs) on {m} samples "
        f"in {time.time() - t0:.0f}s, final loss {np.mean(history[-50:]):.4f}"
    )
    return net


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


# --- checkpoints -------------------------------------------------------------------------------


def checkpoint(net: CameraNet | PointNet, pipeline: PipelineConfig, cfg, data_desc) -> dict:
    """A saved network: its kind, architecture, weights, pre-processing and training config."""
    return {
        "kind": "camera" if isinstance(net, CameraNet) else "point",
        "config": dataclasses.asdict(net.cfg),
        "state_dict": {k: v.cpu() for k, v in net.state_dict().items()},
        "pipeline": pipeline.to_dict(),
        "train_config": dataclasses.asdict(cfg),
        "data": data_desc,
    }
