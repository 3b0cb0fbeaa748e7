"""Training losses (supplementary sec. 1)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .keypoints import OKS_SCALES


def regression_loss(pred, target, weight, scales=None, delta: float = 1.0):
    """L_reg = 1/K sum_k v_k r_k Huber((pred_k - label_k) / s_k), averaged over the batch.

    pred/target [B,K,3], weight [B,K] = v_k * r_k. The Huber term is summed over x, y, z. Scales
    s_k default to the OKS scales, so keypoints that must be located precisely weigh more."""
    s = torch.tensor(OKS_SCALES, dtype=pred.dtype, device=pred.device) if scales is None else scales
    diff = (pred - target) / s.view(1, -1, 1)
    h = F.huber_loss(diff, torch.zeros_like(diff), reduction="none", delta=delta).sum(dim=2)
    return (weight * h).mean()


def segmentation_loss(logits, labels, visible, w_pos: float = 20.0, w_neg: float = 1.0):
    """Weighted binary cross-entropy over points and keypoints, only for visible keypoints.

    logits/labels [B,N,K], visible [B,K]. Averaged over points (the paper sums; averaging keeps
    lambda = 0.1 meaningful whatever N is) and keypoints, then over the batch."""
    w = torch.where(labels > 0.5, w_pos, w_neg) * visible.unsqueeze(1).to(logits.dtype)
    bce = F.binary_cross_entropy_with_logits(logits, labels, reduction="none")
    return (w * bce).mean(dim=1).mean()


def heatmap_targets(kp_uv, visible, image_size: int, size: int, sigma: float):
    """Gaussian targets [B,K,H,H] centred at each keypoint's cell coordinate (cell (i,j) is centred
    at model px (j*S/H, i*S/H)), and target weights [B,K]: visible and inside the heatmap."""
    c = kp_uv * (size / image_size)  # [B,K,2] in cell units
    grid = torch.arange(size, dtype=kp_uv.dtype, device=kp_uv.device)
    gx = torch.exp(-((grid.view(1, 1, -1) - c[..., 0:1]) ** 2) / (2 * sigma**2))  # [B,K,W]
    gy = torch.exp(-((grid.view(1, 1, -1) - c[..., 1:2]) ** 2) / (2 * sigma**2))  # [B,K,H]
    target = gy.unsqueeze(3) * gx.unsqueeze(2)
    inside = (c > -0.5).all(dim=2) & (c < size - 0.5).all(dim=2)
    weight = (visible > 0) & inside & torch.isfinite(c).all(dim=2)
    target = torch.nan_to_num(target) * weight[..., None, None]
    return target, weight.to(kp_uv.dtype)


def heatmap_loss(pred, target, weight):
    """Visibility-weighted MSE: 1/(H'W'K) sum v_k (h - g)^2, averaged over the batch."""
    return ((pred - target) ** 2 * weight[..., None, None]).mean()
