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

Data comes as a dict of arrays (small sets, tests) or as a `shards.ShardSet` read a window of
shards at a time; either way batches are drawn by `shards.IndexSampler` and gathered by
`shards.ShardLoader`. How a stage runs (device, bf16, processes, checkpoints, resume) is its
`RunOptions`; what it learns is its config.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from . import distributed
from .camera_net import CameraNet, check_heatmap_size
from .config import CameraNetConfig, PipelineConfig, PointNetConfig
from .fusion import sample_features, smooth_heatmaps
from .keypoints import FLIP, NAMES, K
from .labels import SEGMENTATION_RADIUS, pseudo_labels, relabelled, segmentation_labels
from .losses import heatmap_loss, heatmap_targets, regression_loss, segmentation_loss
from .point_net import PointNet
from .shards import IndexSampler, ShardLoader, ShardSet, window_shards

# --- how a stage runs ---------------------------------------------------------------------------


@dataclass
class RunOptions:
    """How a training stage runs, not what it learns."""

    device: str = "cpu"
    amp: bool = False  # bf16 autocast of the forward pass (CUDA; allowed on the CPU for tests)
    channels_last: bool = False  # the camera net's memory format (pays on CUDA convolutions)
    memory_mb: float = 0.0  # shard memory budget; 0: the whole set in memory
    checkpoint: Path | None = None  # the stage's resumable checkpoint
    checkpoint_every: int = 0  # steps between checkpoints (0: only at the end)
    resume: bool = False  # continue from `checkpoint` when it exists
    stop_at_step: int = 0  # > 0: stop once this step is done (checkpoint written), resume later
    record: Callable[[dict], None] | None = None  # JSONL records (losses every `record_every`)
    record_every: int = 50
    dist: distributed.Dist = field(default_factory=distributed.Dist)


class Stopped(Exception):
    """A stage stopped at `stop_at_step` before its end; its checkpoint holds the run."""


def _autocast(opts: RunOptions):
    if not opts.amp:
        return contextlib.nullcontext()
    return torch.autocast(device_type=torch.device(opts.device).type, dtype=torch.bfloat16)


def _save_atomic(obj, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    torch.save(obj, tmp)
    os.replace(tmp, path)


class Source:
    """A data set as the training stages read it: a ShardSet, or a dict of arrays seen as one
    shard (everything in memory)."""

    def __init__(self, data):
        if isinstance(data, ShardSet):
            self.shards = data
        else:
            self.shards = _MemoryShards(data)

    def __len__(self) -> int:
        return len(self.shards)

    def window(self, keys, opts: RunOptions) -> int:
        if opts.memory_mb <= 0:
            return self.shards.num_shards
        return window_shards(self.shards, keys, opts.memory_mb)

    def column(self, key: str) -> np.ndarray:
        """One small array over the whole set (labels, counts, boxes)."""
        return self.shards.read_all([key])[key]


class _MemoryShards:
    """A dict of arrays with ShardSet's reading interface: one shard holding every sample."""

    def __init__(self, data: dict):
        self.data = data
        m = len(data["kp2d"])
        self.counts = np.asarray([m], np.int64)
        self.offsets = np.asarray([0, m], np.int64)
        self.num_shards = 1

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def shard_of(self, index):
        return np.zeros(len(index), np.int64)

    def shard_bytes(self, keys) -> int:
        return sum(self.data[k].nbytes for k in keys)

    def read(self, shard: int, keys) -> dict:
        return {k: self.data[k] for k in keys}

    def read_all(self, keys) -> dict:
        return {k: self.data[k] for k in keys}


# What labels on the 2D labels' rays read besides: the camera and crop that make a pixel a ray.
RAY_LABEL_KEYS = ("kp2d_occluded", "crop", "intrinsic", "extrinsic", "frame_yaw")
# what a round's pseudo labels hold (stream_labels, next_round_labels)
LABEL_KEYS = ("kp3d", "weight", "visible")


def label_settings(t_r: float, pipeline: PipelineConfig, point: TrainPointConfig, round_: int) -> dict:
    """What round `round_`'s labels depend on besides the data and (after the first round) the
    nets: the settings stream_labels() and next_round_labels() read, and nothing else of the
    recipe, so that a run given more rounds can keep the labels it made."""
    keep = ("depth_correction", "occluded_weight", "seg_radius", "snap_to_rays") + (
        ("self_train",) if round_ > 1 else ()
    )
    return {"t_r": t_r, "pipeline": dataclasses.asdict(pipeline), **{k: getattr(point, k) for k in keep}}


def stream_labels(data, cfg: PipelineConfig, t_r: float, point: TrainPointConfig) -> dict:
    """Pseudo labels of every sample of a dict or ShardSet (small: [M,K] and [M,K,3]), computed one
    shard at a time, as `point` (its label settings) says."""
    source = data if isinstance(data, Source) else Source(data)
    keys = ("kp2d", "kp2d_visible", "points_xyz", "points_uv", "points_count", "box3d", "sensor_xyz")
    if point.occluded_weight > 0 or point.snap_to_rays:
        keys += RAY_LABEL_KEYS
    rays = {
        "occluded_weight": point.occluded_weight,
        "occluded_radius": point.seg_radius,
        "snap_to_rays": point.snap_to_rays,
    }
    parts = [
        # chunks of 128: eq. 1 holds [chunk, K, P, 2] float64 distances (P: the widest person)
        pseudo_labels(source.shards.read(i, keys), cfg, t_r, point.depth_correction, 128, **rays)
        for i in range(source.shards.num_shards)
    ]
    return {k: np.concatenate([p[k] for p in parts], axis=0) for k in LABEL_KEYS}


@torch.no_grad()
def next_round_labels(
    data, first: dict, nets: tuple, smoothed, pipeline: PipelineConfig, cfg, device="cpu"
) -> dict:
    """labels.relabelled() of every sample of a dict or ShardSet, one shard at a time: the first
    round's labels `first` and the mean answer of the round before's `nets` (fusion, LiDAR-only;
    on the CPU), the fusion net reading `smoothed` as train_point() does (the camera net, whose
    heatmaps are computed per shard as served, or every sample's smoothed heatmaps). `cfg`: the
    TrainPointConfig (self_train)."""
    source = data if isinstance(data, Source) else Source(data)
    keys = ("serve_xyz", "serve_uv", "kp2d", "kp2d_visible", "box3d") + RAY_LABEL_KEYS
    camera = isinstance(smoothed, torch.nn.Module)
    heatmaps = shard_heatmaps(smoothed.to(device).eval(), pipeline, device) if camera else None
    fusion, lidar = (net.cpu().eval() for net in nets)
    offsets, parts = source.shards.offsets, []
    for i in range(source.shards.num_shards):
        mine = slice(int(offsets[i]), int(offsets[i + 1]))
        arrays = source.shards.read(i, keys + ("image",) if camera else keys)
        sm = heatmaps(i, arrays)["smoothed"] if camera else smoothed[mine]
        xyz, uv = arrays["serve_xyz"], arrays["serve_uv"]
        pred = (
            predict_points(fusion, xyz, uv, sm, pipeline) + predict_points(lidar, xyz, uv, None, pipeline)
        ) / 2
        parts.append(relabelled({k: v[mine] for k, v in first.items()}, arrays, pred, cfg.self_train))
    return {k: np.concatenate([p[k] for p in parts], axis=0) for k in LABEL_KEYS}


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
    start_step: int = 0,
    history: list[float] | None = None,
    after_step: Callable[[int, list[float], float], bool] | None = None,
    batch_size: int = 1,
    autocast=contextlib.nullcontext,
    mean=float,
) -> list[float]:
    """The training loop of both networks: `steps` optimizer steps on `batch_loss(step)` (a scalar
    tensor), the learning rate of each step from `lr_at(step, total_steps)`. With `time_budget_s`
    > 0 the run stops early when the budget runs out (see StepBudget). A resumed run starts at
    `start_step` with the loss `history` so far. `after_step(steps_done, history, lr)` runs after
    every step (checkpoints, logs) and stops the run by returning True. `mean` turns a loss into
    the number logged (the mean over processes under DDP). The bar counts samples (samples/s,
    ETA). Returns the loss per step and leaves the network in eval mode."""
    budget = StepBudget(steps, time_budget_s, min_steps, clock)
    net.train()
    step, history = start_step, list(history or [])
    ema = None
    bar = tqdm(
        total=budget.total * batch_size,
        initial=step * batch_size,
        desc=desc,
        unit="sample",
        unit_scale=True,
        mininterval=5.0,
    )
    while step < budget.total:
        lr = lr_at(step, budget.total)
        for g in opt.param_groups:
            g["lr"] = lr
        with autocast():
            loss = batch_loss(step)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        bar.total = budget.update(step) * batch_size
        history.append(mean(loss))
        ema = history[-1] if ema is None else 0.98 * ema + 0.02 * history[-1]
        bar.update(batch_size)
        bar.set_postfix(loss=f"{ema:.3e}", refresh=False)
        if after_step is not None and after_step(step, history, lr):
            break
    bar.close()
    net.eval()
    return history


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
    # > 0 (with a net that has a facing head): weight of the facing target's loss
    facing_weight: float = 0.0
    # True: the trained net is asked about each crop and its mirror (camera_net.FlipTest) wherever
    # it answers: heatmaps for the point nets, evaluation, the bundle. Training itself is the same.
    flip_test: bool = False
    steps: int = 0  # > 0: exactly this many steps (overrides epochs)
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


# A person is judged side-on (no facing target) when the left-right spread is below this share of
# the crop: about 4 px at S = 128.
SIDE_ON = 0.03


def facing_target(kp: torch.Tensor, vis: torch.Tensor, image_size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """From 2D labels [B,K,2] (after augmentation): whether each person faces the camera (their
    left shoulder and hip to the right of their right ones in the image) and whether that is
    known (all four visible, not side-on). A flipped crop keeps its target: flipping mirrors x and
    exchanges left and right."""
    ls, rs, lh, rh = (NAMES.index(n) for n in ("left_shoulder", "right_shoulder", "left_hip", "right_hip"))
    dx = (kp[:, ls, 0] - kp[:, rs, 0]) + (kp[:, lh, 0] - kp[:, rh, 0])
    seen = (vis[:, [ls, rs, lh, rh]] > 0).all(dim=1)
    return (dx > 0).float(), (seen & (dx.abs() > SIDE_ON * image_size)).float()


def facing_loss(logit: torch.Tensor, front: torch.Tensor, known: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy over the persons whose facing is known."""
    per = F.binary_cross_entropy_with_logits(logit, front, reduction="none")
    return (per * known).sum() / known.sum().clamp(min=1.0)


class Stage:
    """Checkpoints and resumption of one network's training: the network, its optimizer, the
    sampler, the augmentation generator, the step and the loss history. A resumed stage continues
    to the same weights as an uninterrupted one (same device and process count)."""

    def __init__(self, name: str, net, opt, sampler: IndexSampler, gen: torch.Generator, opts: RunOptions):
        self.name, self.net, self.opt, self.sampler, self.gen, self.opts = name, net, opt, sampler, gen, opts
        self.steps = 0
        self.stopped = False
        self.batch_size = 1
        self._mark = (time.monotonic(), 0)  # (time, step) of the last record

    def restore(self) -> tuple[int, list[float]]:
        path = self.opts.checkpoint
        if not (self.opts.resume and path is not None and Path(path).exists()):
            return 0, []
        state = torch.load(path, map_location="cpu", weights_only=False)
        if state.get("stage") != self.name:
            raise ValueError(f"{path}: a checkpoint of stage {state.get('stage')!r}, not {self.name!r}")
        self.net.load_state_dict(state["net"])
        self.opt.load_state_dict(state["opt"])
        self.sampler.load_state_dict(state["sampler"])
        self.gen.set_state(state["gen"])
        return int(state["step"]), list(state["history"])

    def save(self, step: int, history: list[float]) -> None:
        if self.opts.checkpoint is None or not self.opts.dist.main:
            return
        state = {
            "stage": self.name,
            "step": step,
            "history": history,
            "net": {k: v.detach().cpu() for k, v in self.net.state_dict().items()},
            "opt": self.opt.state_dict(),
            "sampler": self.sampler.state_dict(),
            "gen": self.gen.get_state(),
        }
        _save_atomic(state, Path(self.opts.checkpoint))

    def after_step(self, step: int, history: list[float], lr: float) -> bool:
        o = self.opts
        every = max(1, o.record_every)
        if o.record is not None and o.dist.main and (step % every == 0 or step == self.steps):
            window = history[-every:]
            now, (then, at) = time.monotonic(), self._mark
            self._mark = (now, step)
            rec = {
                "stage": self.name,
                "step": step,
                "loss": float(np.mean(window)),
                "last": history[-1],
                "lr": lr,
            }
            rec["samples_per_s"] = round((step - at) * self.batch_size / max(now - then, 1e-9), 1)
            if torch.device(o.device).type == "cuda":
                rec["cuda_max_memory_gb"] = round(torch.cuda.max_memory_allocated() / 2**30, 3)
            o.record(rec)
        stop = 0 < o.stop_at_step <= step < self.steps
        if step == self.steps or stop or (o.checkpoint_every > 0 and step % o.checkpoint_every == 0):
            self.save(step, history)
        self.stopped = stop
        return stop

    def run(self, batch_loss, lr_at, steps: int, *, time_budget_s: float, min_steps: int, batch_size: int):
        if time_budget_s > 0 and (self.opts.resume or self.opts.stop_at_step):
            raise ValueError("a wall-clock budget cannot be resumed: give a number of steps")
        self.steps, self.batch_size = steps, batch_size
        start, history = self.restore()
        self._mark = (time.monotonic(), start)
        history = fit(
            self.net,
            self.opt,
            batch_loss,
            lr_at,
            steps,
            time_budget_s=time_budget_s,
            min_steps=min_steps,
            desc=self.name,
            start_step=start,
            history=history,
            after_step=self.after_step,
            batch_size=batch_size,
            autocast=lambda: _autocast(self.opts),
            mean=self.opts.dist.mean,
        )
        if self.stopped:
            raise Stopped(f"{self.name}: stopped after step {len(history)} of {steps}")
        return history


def train_camera(
    data,
    pipeline: PipelineConfig,
    net_cfg: CameraNetConfig,
    cfg: TrainCameraConfig,
    device: str = "cpu",
    log=print,
    opts: RunOptions | None = None,
) -> CameraNet:
    """The camera net from 2D labels. `data`: a dict of arrays or a ShardSet."""
    check_heatmap_size(pipeline.image_size, pipeline.heatmap_size, net_cfg)
    opts = opts or RunOptions(device=device)
    device, d = opts.device, opts.dist
    gen, rng = seed_everything(cfg.seed)
    net = CameraNet(net_cfg).to(device)
    if opts.channels_last:
        net = net.to(memory_format=torch.channels_last)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    source = Source(data)
    m = len(source)
    steps = cfg.steps if cfg.steps > 0 else int(round(cfg.epochs * max(1, m // cfg.batch_size)))
    keys = ("image", "kp2d", "kp2d_visible")
    window = source.window(keys, opts)
    sampler = IndexSampler(source.shards, np.ones(m, bool), cfg.batch_size, window, rng)
    loader = ShardLoader(source.shards, keys, 2 * window)
    model = distributed.wrap(net, d, device)
    stage = Stage("camera", net, opt, sampler, gen, opts)

    def lr_at(step, total):
        return cfg.lr * 0.1 ** sum(step / total >= f for f in cfg.decay_at)

    def batch_loss(_step):
        idx = np.sort(sampler.next())
        loader.prefetch(sampler.upcoming_shards())
        b = loader.gather(idx)
        x = to_input(b["image"], device)
        kp = torch.from_numpy(b["kp2d"]).to(device)
        vis = torch.from_numpy(b["kp2d_visible"].astype(np.float32)).to(device)
        # the whole global batch is augmented by every process (one random stream), each trains on its slice
        x, kp, vis = augment(x, kp, vis, cfg, gen)
        mine = d.slice(len(idx))
        x, kp, vis = x[mine], kp[mine], vis[mine]
        target, weight = heatmap_targets(kp, vis, pipeline.image_size, pipeline.heatmap_size, cfg.sigma_cells)
        x = normalize(x, pipeline)
        if opts.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        if cfg.facing_weight <= 0:
            return heatmap_loss(model(x).float(), target, weight)
        heatmaps, facing = model(x, with_facing=True)
        front, known = facing_target(kp, vis, pipeline.image_size)
        return heatmap_loss(heatmaps.float(), target, weight) + cfg.facing_weight * facing_loss(
            facing.float(), front, known
        )

    t0 = time.time()
    try:
        history = stage.run(
            batch_loss, lr_at, steps, time_budget_s=cfg.time_budget_s, min_steps=10, batch_size=cfg.batch_size
        )
    finally:
        loader.close()
    net.loss_history = history
    net.trained_epochs = len(history) * cfg.batch_size / m
    log(
        f"camera: {len(history)} steps ({net.trained_epochs:.1f} epochs) in {time.time() - t0:.0f}s, "
        f"final loss {np.mean(history[-50:]):.3e}"
    )
    return net.to(memory_format=torch.contiguous_format)


@torch.no_grad()
def predict_heatmaps(
    net: CameraNet, images: np.ndarray, pipeline: PipelineConfig, device="cpu", batch=256, progress=True
):
    """Raw (unsmoothed) heatmaps [M,K,H',W'] for uint8 crops [M,S,S,3]."""
    net.eval()
    out = []
    chunks = range(0, len(images), batch)
    if progress:
        chunks = tqdm(chunks, desc="heatmaps", unit="batch", mininterval=5.0, leave=False)
    for a in chunks:
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
    seg_radius: float = SEGMENTATION_RADIUS  # positive radius r, in units of S
    w_pos: float = 20.0
    w_neg: float = 1.0
    # Uniform in [-x, x] about z (the paper: [0, 2 pi)); docs/results-choices.md says why 20 by default.
    rotate_deg: float = 20.0
    time_budget_s: float = 0.0  # opt-in: > 0 stops (with the schedule compressed) when this runs out
    seed: int = 0
    depth_correction: bool = False  # pseudo labels pushed along the rays (labels.depth_offsets)
    # > 0: occluded 2D labels that no point is near get a label on their ray at the box centre's
    # depth, at this weight (labels.occluded_labels; docs/TRAINING.md, "Labels for occluded keypoints")
    occluded_weight: float = 0.0
    # each eq. 1 label moved onto its 2D label's camera ray at its own depth (labels.snapped_to_label_rays)
    snap_to_rays: bool = False
    # > 0: both point nets trained again, self_train_rounds times, each round on labels.relabelled()
    # from the round before's blend; the 2D labels without a first-round label at this weight
    # (docs/TRAINING.md, "Self-training")
    self_train: float = 0.0
    self_train_rounds: int = 1


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


def point_batch(xyz, uv, smoothed, pipeline: PipelineConfig):
    """Network input [B,N,3(+K)] from xyz [B,N,3], uv [B,N,2] and smoothed heatmaps (or None)."""
    if smoothed is None:
        return xyz
    return torch.cat([xyz, sample_features(smoothed, uv, pipeline.image_size, pipeline.sampling)], dim=2)


def shard_heatmaps(camera: torch.nn.Module, pipeline: PipelineConfig, device: str):
    """A ShardLoader transform: a shard's images -> the camera net's smoothed heatmaps (what the
    fusion net samples), computed once per shard load; the images are dropped."""

    def transform(_shard: int, arrays: dict) -> dict:
        raw = predict_heatmaps(camera, arrays.pop("image"), pipeline, device, progress=False)
        t = torch.from_numpy(raw)
        arrays["smoothed"] = smooth_heatmaps(t, pipeline.smoothing_kernel, pipeline.smoothing_sigma).numpy()
        return arrays

    return transform


def train_point(
    data,
    labels: dict | None,
    smoothed,
    pipeline: PipelineConfig,
    net_cfg: PointNetConfig,
    cfg: TrainPointConfig,
    device: str = "cpu",
    desc: str = "point",
    log=print,
    opts: RunOptions | None = None,
    t_r: float = 200.0,
) -> PointNet:
    """data: a dict of arrays or a ShardSet; labels: pseudo_labels() of every sample (None: computed
    here, shard by shard, with `t_r`); smoothed (fusion only): [M,K,H,W] smoothed camera heatmaps
    of every sample, or the frozen CameraNet whose heatmaps are computed per shard as it is read."""
    opts = opts or RunOptions(device=device)
    device, d = opts.device, opts.dist
    if cfg.fusion != (smoothed is not None) or net_cfg.in_features != (3 + K if cfg.fusion else 3):
        raise ValueError("fusion needs smoothed heatmaps and 3+K input features; LiDAR-only neither")
    gen, rng = seed_everything(cfg.seed)
    source = Source(data)
    if labels is None:
        labels = stream_labels(source, pipeline, t_r, cfg)
    counts_np = source.column("points_count")
    usable_mask = (counts_np > 0) & (labels["weight"] > 0).any(axis=1)
    m = int(usable_mask.sum())
    if m == 0:
        raise ValueError("no training sample has points and a pseudo label")
    kp3d = torch.from_numpy(labels["kp3d"])
    weight = torch.from_numpy(labels["weight"])
    vis = torch.from_numpy(labels["visible"].astype(np.float32))
    keys = ["points_xyz", "points_uv", "points_count", "kp2d"]
    transform = None
    sm_all = None
    if isinstance(smoothed, torch.nn.Module):  # a CameraNet, or one under FlipTest
        keys.append("image")
        transform = shard_heatmaps(smoothed.to(device).eval(), pipeline, device)
    elif smoothed is not None:
        sm_all = torch.from_numpy(smoothed)
    n, s = pipeline.num_points, pipeline.image_size

    net = PointNet(net_cfg).to(device)
    if cfg.optimizer == "adam":
        opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    else:
        opt = torch.optim.SGD(
            net.parameters(), lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay, nesterov=True
        )
    steps = cfg.steps if cfg.steps > 0 else int(round(cfg.epochs * max(1, m // cfg.batch_size)))
    window = source.window(keys, opts)
    sampler = IndexSampler(source.shards, usable_mask, cfg.batch_size, window, rng)
    loader = ShardLoader(source.shards, keys, 2 * window, transform)
    model = distributed.wrap(net, d, device)
    stage = Stage(desc, net, opt, sampler, gen, opts)

    def lr_at(step, total):
        if step < cfg.warmup_steps:
            return cfg.lr * (step + 1) / cfg.warmup_steps
        t = (step - cfg.warmup_steps) / max(1, total - cfg.warmup_steps)
        return cfg.lr * 0.5 * (1 + math.cos(math.pi * min(1.0, t)))

    def batch_loss(_step):
        idx_np = sampler.next()
        loader.prefetch(sampler.upcoming_shards())
        b = loader.gather(idx_np)
        idx = torch.from_numpy(idx_np)
        xyz_b, uv_b = torch.from_numpy(b["points_xyz"]), torch.from_numpy(b["points_uv"])
        # the point axis is the whole set's widest person (ShardSet pads every shard to it)
        sel = select_points(torch.from_numpy(b["points_count"].astype(np.int64)), n, xyz_b.shape[1], gen)
        xyz = torch.gather(xyz_b, 1, sel.unsqueeze(2).expand(-1, -1, 3))
        uv = torch.gather(uv_b, 1, sel.unsqueeze(2).expand(-1, -1, 2))
        target = kp3d[idx]
        if cfg.rotate_deg > 0:
            ang = (torch.rand(len(idx), generator=gen) * 2 - 1) * math.radians(cfg.rotate_deg)
            xyz, target = rotate_z(xyz, ang), rotate_z(target, ang)
        if transform is not None:
            sm = torch.from_numpy(b["smoothed"])
        else:
            sm = None if sm_all is None else sm_all[idx]
        # every process builds the global batch (one random stream) and trains on its slice
        mine = d.slice(len(idx))
        x = point_batch(xyz[mine], uv[mine], None if sm is None else sm[mine], pipeline).to(device)
        pred, seg_logits = model(x)
        pred, seg_logits = pred.float(), seg_logits.float()
        loss = regression_loss(pred, target[mine].to(device), weight[idx][mine].to(device))
        if cfg.seg:
            seg_lab = segmentation_labels(
                torch.from_numpy(b["kp2d"])[mine], vis[idx][mine], uv[mine], s, cfg.seg_radius
            ).to(device)
            loss = loss + cfg.seg_weight * segmentation_loss(
                seg_logits, seg_lab, vis[idx][mine].to(device), cfg.w_pos, cfg.w_neg
            )
        return loss

    t0 = time.time()
    try:
        history = stage.run(
            batch_loss,
            lr_at,
            steps,
            time_budget_s=cfg.time_budget_s,
            min_steps=2 * cfg.warmup_steps,
            batch_size=cfg.batch_size,
        )
    finally:
        loader.close()
    net.loss_history = history
    net.trained_epochs = len(history) * cfg.batch_size / m
    log(
        f"{desc}: {len(history)} steps ({net.trained_epochs:.1f} epochs) on {m} samples "
        f"in {time.time() - t0:.0f}s, final loss {np.mean(history[-50:]):.4f}"
    )
    return net


@torch.no_grad()
def predict_points(
    net: PointNet, xyz: np.ndarray, uv: np.ndarray, smoothed, pipeline: PipelineConfig, batch=512
):
    """Keypoints [M,K,3] for the serve points xyz [M,N,3] / uv [M,N,2]."""
    net.eval()
    out = []
    for a in range(0, len(xyz), batch):
        sm = None if smoothed is None else torch.from_numpy(smoothed[a : a + batch])
        x = point_batch(
            torch.from_numpy(xyz[a : a + batch]), torch.from_numpy(uv[a : a + batch]), sm, pipeline
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
