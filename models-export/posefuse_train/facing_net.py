"""One point network that needs no heading: a first network trained with rotation over [0, 2π)
reads the body's facing from the points (and the camera's evidence on them); the points are turned
so the body faces +x, the frame a box-heading network is at its best in; that network answers,
its own answer's facing turns the points again for `passes` more rounds (the serving path's
heading refinement, done inside the graph), and the answer is turned back into the input frame.

It is exported as an ordinary point network (the same input and outputs), so a bundle carrying it
needs no new server code and one inference per person (docs/BUNDLE.md, "Facing inside the point
network"). The facing follows crates/core/src/pipeline/facing.rs: left minus right for the
shoulders and the hips, summed horizontally, turned a quarter clockwise.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .keypoints import NAMES

_LS, _RS, _LH, _RH = (NAMES.index(n) for n in ("left_shoulder", "right_shoulder", "left_hip", "right_hip"))

# Below this horizontal left-right length (metres) the keypoints point nowhere and the points are
# not turned; facing.rs uses the same micrometre.
_NOWHERE_M = 1e-6


def facing_cos_sin(keypoints: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """keypoints [B,K,3] -> (cos, sin) of each body's facing yaw [B]; (1, 0) where the shoulders
    and hips cancel."""
    left = keypoints[:, _LS, :2] - keypoints[:, _RS, :2] + keypoints[:, _LH, :2] - keypoints[:, _RH, :2]
    lx, ly = left[:, 0], left[:, 1]
    norm = torch.sqrt(lx * lx + ly * ly)
    ok = norm > _NOWHERE_M
    safe = torch.where(ok, norm, torch.ones_like(norm))
    # left (lx, ly) turned clockwise is forward (ly, −lx)
    cos = torch.where(ok, ly / safe, torch.ones_like(norm))
    sin = torch.where(ok, -lx / safe, torch.zeros_like(norm))
    return cos, sin


def turn(xyz: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """Rotates [B,R,3] about z by the per-row angle whose cos and sin are given [B]."""
    c, s = cos[:, None], sin[:, None]
    x, y = xyz[..., 0], xyz[..., 1]
    return torch.stack([c * x - s * y, s * x + c * y, xyz[..., 2]], dim=-1)


class FacingPointNet(nn.Module):
    """`first` (rotation-free) finds the facing; `second` (box-heading frame) answers in it."""

    def __init__(
        self, first: nn.Module, second: nn.Module, passes: int = 1, turns: int = 1, agree_deg: float = 0.0
    ):
        super().__init__()
        if first.cfg.in_features != second.cfg.in_features:
            raise ValueError("both networks must take the same point features")
        if passes < 0 or turns < 1:
            raise ValueError("passes must be >= 0 and turns >= 1")
        self.first, self.second, self.passes, self.turns = first, second, passes, turns
        self.cfg = second.cfg
        # > 0: where the first network's facing is within this many degrees of the box heading,
        # the box frame is kept as given (exact headings are better than any estimate).
        self.agree_cos = math.cos(math.radians(agree_deg)) if agree_deg > 0 else 2.0

    def first_facing(self, xyz: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The first network's facing, its answers at `turns` evenly spaced turns of the input
        turned back and averaged (the network was trained at every angle, so each turn is another
        opinion)."""
        b = xyz.shape[0]
        angles = torch.arange(self.turns, dtype=xyz.dtype) * (2 * math.pi / self.turns)
        cos, sin = torch.cos(angles).repeat_interleave(b), torch.sin(angles).repeat_interleave(b)
        many = turn(xyz.repeat(self.turns, 1, 1), cos, sin)
        keypoints, _ = self.first(torch.cat([many, features.repeat(self.turns, 1, 1)], dim=-1))
        back = turn(keypoints, cos, -sin).reshape(self.turns, b, *keypoints.shape[1:])
        return facing_cos_sin(back.mean(dim=0))

    def forward(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """points [B,N,C] -> keypoints [B,K,3] in the input frame, segmentation logits [B,N,K]."""
        xyz, features = points[..., :3], points[..., 3:]
        cos, sin = self.first_facing(xyz, features)
        agree = cos > self.agree_cos
        for i in range(self.passes + 1):
            # the body turned to face +x: by minus its facing
            local = turn(xyz, cos, -sin)
            keypoints, seg = self.second(torch.cat([local, features], dim=-1))
            if i < self.passes:
                c2, s2 = facing_cos_sin(keypoints)
                cos, sin = cos * c2 - sin * s2, sin * c2 + cos * s2
        keypoints = turn(keypoints, cos, sin)
        if self.agree_cos <= 1.0:
            as_given, seg_as_given = self.second(points)
            keypoints = torch.where(agree[:, None, None], as_given, keypoints)
            seg = torch.where(agree[:, None, None], seg_as_given, seg)
        return keypoints, seg
