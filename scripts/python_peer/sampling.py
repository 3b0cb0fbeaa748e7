"""The Python peer's heatmap sampling (scripts/python_peer/server.py), NumPy only, so that the
project's tests can check it against the golden vectors without the peer's own packages."""

from __future__ import annotations

import numpy as np


def sample(smooth: np.ndarray, uv: np.ndarray, image_size: int, sampling: str) -> np.ndarray:
    """docs/BUNDLE.md, "Heatmap grid and sampling": the cell a point falls in (`nearest`), or the
    value between the four cells around it, cell j's centre at j * S / H (`bilinear`). `smooth`
    [K,H,W], `uv` [N,2] finite model pixels of an S = `image_size` crop -> [N,K]."""
    _, h, w = smooth.shape
    x, y = uv[:, 0] * np.float32(w / image_size), uv[:, 1] * np.float32(h / image_size)
    if sampling == "nearest":
        j = np.clip(np.floor(x + np.float32(0.5)), 0, w - 1).astype(int)
        i = np.clip(np.floor(y + np.float32(0.5)), 0, h - 1).astype(int)
        return smooth[:, i, j].T
    x, y = np.clip(x, 0, w - 1), np.clip(y, 0, h - 1)
    j0, i0 = np.floor(x).astype(int), np.floor(y).astype(int)
    j1, i1 = np.minimum(j0 + 1, w - 1), np.minimum(i0 + 1, h - 1)
    tx, ty = x - j0, y - i0
    top = smooth[:, i0, j0] * (1 - tx) + smooth[:, i0, j1] * tx
    bottom = smooth[:, i1, j0] * (1 - tx) + smooth[:, i1, j1] * tx
    return (top * (1 - ty) + bottom * ty).T
