"""Modality fusion and heatmap decoding, bit-for-bit the server's (crates/core/src/pipeline/fusion.rs,
lift.rs):
Gaussian smoothing with zero padding, per-point cell sampling, argmax + quarter-cell decoding."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


def gaussian_1d(size: int, sigma: float) -> np.ndarray:
    c = (size - 1) / 2.0
    g = np.exp(-((np.arange(size, dtype=np.float64) - c) ** 2) / (2.0 * float(sigma) ** 2))
    return (g / g.sum()).astype(np.float32)


def gaussian_kernel(size: int, sigma: float) -> np.ndarray:
    """size x size, normalized to sum 1 (outer product of the normalized 1D factor)."""
    g = gaussian_1d(size, sigma)
    return np.outer(g, g).astype(np.float32)


def smooth_heatmaps(heatmaps: torch.Tensor, size: int, sigma: float) -> torch.Tensor:
    """[B,K,H,W] -> same shape; each channel convolved with the kernel, zero padding."""
    g = torch.from_numpy(gaussian_1d(size, sigma)).to(heatmaps.device, heatmaps.dtype)
    k = heatmaps.shape[1]
    r = size // 2
    # Separable, rows then columns, like the server (equal to the 2D kernel up to rounding).
    x = F.conv2d(heatmaps, g.view(1, 1, 1, size).expand(k, 1, 1, size), padding=(0, r), groups=k)
    return F.conv2d(x, g.view(1, 1, size, 1).expand(k, 1, size, 1), padding=(r, 0), groups=k)


def cell_index(x: np.ndarray | torch.Tensor, cells: int, image_size: int):
    """floor(x * cells / S + 0.5) clamped to [0, cells-1], in float32 like the server."""
    if isinstance(x, torch.Tensor):
        m = torch.floor(x.float() * float(cells) / float(image_size) + 0.5)
        return m.clamp(0, cells - 1).long()
    x = np.asarray(x, dtype=np.float32)
    m = np.floor(x * np.float32(cells) / np.float32(image_size) + np.float32(0.5))
    return np.clip(np.nan_to_num(m, nan=0.0), 0, cells - 1).astype(np.int64)


def sample_features(
    smoothed: torch.Tensor, uv: torch.Tensor, image_size: int, sampling: str = "nearest"
) -> torch.Tensor:
    """smoothed [B,K,H,W], uv [B,N,2] model px -> [B,N,K]; a NaN uv gives zeros. `sampling`:
    "nearest" (the paper's cell) or "bilinear" (between the four cells around the point)."""
    b, k, h, w = smoothed.shape
    finite = torch.isfinite(uv).all(dim=2)  # [B,N]
    safe = torch.where(finite.unsqueeze(2), uv, torch.zeros_like(uv))
    flat = smoothed.reshape(b, k, h * w)

    def at(i, j):
        idx = (i * w + j).unsqueeze(1).expand(b, k, -1)  # [B,K,N]
        return torch.gather(flat, 2, idx).transpose(1, 2)

    if sampling == "nearest":
        feats = at(cell_index(safe[..., 1], h, image_size), cell_index(safe[..., 0], w, image_size))
    elif sampling == "bilinear":
        i0, ty = bilinear_cell(safe[..., 1], h, image_size)
        j0, tx = bilinear_cell(safe[..., 0], w, image_size)
        i1, j1 = (i0 + 1).clamp(max=h - 1), (j0 + 1).clamp(max=w - 1)
        tx, ty = tx.unsqueeze(2), ty.unsqueeze(2)
        top = (1 - tx) * at(i0, j0) + tx * at(i0, j1)
        bottom = (1 - tx) * at(i1, j0) + tx * at(i1, j1)
        feats = (1 - ty) * top + ty * bottom
    else:
        raise ValueError(f"sampling {sampling!r}: nearest or bilinear")
    return feats * finite.unsqueeze(2).to(feats.dtype)


def bilinear_cell(x: torch.Tensor, cells: int, image_size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The lower of the two cells around model pixel x and the weight of the upper one, in float32
    like the server: c = x·W'/S clamped to [0, W'-1] (cell j's centre is at x = j·S/W')."""
    c = (x.float() * float(cells) / float(image_size)).clamp(0, cells - 1)
    lo = torch.floor(c).clamp(max=max(cells - 2, 0))
    return lo.long(), c - lo


def smoothed(raw: np.ndarray, cfg, batch: int = 2048) -> np.ndarray:
    """smooth_heatmaps over a whole numpy array [M,K,H,W] in batches, with the bundle's kernel."""
    out = np.empty_like(raw)
    for a in range(0, len(raw), batch):
        t = torch.from_numpy(raw[a : a + batch])
        out[a : a + batch] = smooth_heatmaps(t, cfg.smoothing_kernel, cfg.smoothing_sigma).numpy()
    return out


def decode_heatmaps(heatmaps: np.ndarray, image_size: int) -> tuple[np.ndarray, np.ndarray]:
    """[B,K,H,W] -> (model px [B,K,2], peak score [B,K]): the argmax cell moved a quarter cell
    toward its larger neighbour (no shift at the border or on ties), cell (i,j) -> (j*S/W, i*S/H)."""
    hm = np.asarray(heatmaps, dtype=np.float32)
    b, k, h, w = hm.shape
    flat = hm.reshape(b, k, h * w)
    best = flat.argmax(axis=2)  # first maximum, like the server's strict '>' scan
    score = np.take_along_axis(flat, best[..., None], axis=2)[..., 0]
    i, j = best // w, best % w

    def at(ii, jj):
        return np.take_along_axis(flat, (ii * w + jj)[..., None], axis=2)[..., 0]

    def shift(lo_ok, hi_ok, lo, hi):
        s = np.where(hi > lo, 0.25, np.where(lo > hi, -0.25, 0.0))
        return np.where(lo_ok & hi_ok, s, 0.0).astype(np.float32)

    jl, jh = np.clip(j - 1, 0, w - 1), np.clip(j + 1, 0, w - 1)
    il, ih = np.clip(i - 1, 0, h - 1), np.clip(i + 1, 0, h - 1)
    dx = shift(j > 0, j + 1 < w, at(i, jl), at(i, jh))
    dy = shift(i > 0, i + 1 < h, at(il, j), at(ih, j))
    sx, sy = np.float32(image_size / w), np.float32(image_size / h)
    uv = np.stack([(j.astype(np.float32) + dx) * sx, (i.astype(np.float32) + dy) * sy], axis=2)
    return uv.astype(np.float32), score
