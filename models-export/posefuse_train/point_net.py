"""Point network: a PointNet encoder (shared per-point MLP + max-pool) with a regression head for
K 3D keypoints and an auxiliary per-point segmentation branch that splits off early (local
features concatenated with the global feature), as in the paper's sec. 3.3."""

from __future__ import annotations

import torch
from torch import nn

from .config import PointNetConfig
from .keypoints import K


def mlp(cin: int, channels) -> tuple[nn.Sequential, int]:
    """Linear + BatchNorm + ReLU layers acting on rows [R, C]; applied to points flattened to
    [B*N, C] it is PointNet's shared MLP (faster on CPU than 1x1 convolutions)."""
    layers = []
    for c in channels:
        layers += [nn.Linear(cin, c, bias=False), nn.BatchNorm1d(c), nn.ReLU(inplace=True)]
        cin = c
    return nn.Sequential(*layers), cin


class PointNet(nn.Module):
    def __init__(self, cfg: PointNetConfig):
        super().__init__()
        self.cfg = cfg
        self.local, c_local = mlp(cfg.in_features, cfg.local_channels)
        self.encoder, c_global = mlp(c_local, cfg.global_channels)
        self.head, c_head = mlp(c_global, cfg.head_channels)
        self.head_out = nn.Linear(c_head, 3 * K)
        # The segmentation branch sees [local, global] per point. Its first layer is split in two
        # (W [l; g] = W_l l + W_g g) so the global half runs once per person, not once per point.
        c0 = cfg.seg_channels[0]
        self.seg_local = nn.Linear(c_local, c0, bias=False)
        self.seg_global = nn.Linear(c_global, c0, bias=False)
        self.seg_bn = nn.BatchNorm1d(c0)
        self.seg, c_seg = mlp(c0, cfg.seg_channels[1:])
        self.seg_out = nn.Linear(c_seg, K)

    def forward(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """points [B,N,C] -> keypoints [B,K,3], segmentation logits [B,N,K]."""
        _, n, c = points.shape
        local = self.local(points.reshape(-1, c))  # [B*N, C1]
        per_point = self.encoder(local)
        glob = per_point.reshape(-1, n, per_point.shape[1]).amax(dim=1)  # [B, C2]
        keypoints = self.head_out(self.head(glob)).reshape(-1, K, 3)
        s = self.seg_local(local).reshape(-1, n, self.seg_bn.num_features) + self.seg_global(glob).unsqueeze(
            1
        )
        s = torch.relu(self.seg_bn(s.reshape(-1, self.seg_bn.num_features)))
        seg = self.seg_out(self.seg(s))
        return keypoints, seg.reshape(-1, n, K)


class Blend(nn.Module):
    """The mean of several point networks' answers, each given the leading point features it takes
    (a LiDAR-only network the xyz of a fusion network's input). The fusion and LiDAR-only networks
    err differently (docs/RESULTS.md, "Where the camera's evidence goes"), so their mean beats
    either, and it beats two networks of one modality."""

    def __init__(self, nets: list[nn.Module], names: list[str]):
        super().__init__()
        if len(nets) < 2 or len(names) != len(nets):
            raise ValueError("a blend takes two or more networks, each named")
        self.nets, self.names = nn.ModuleList(nets), list(names)
        self.cfg = max((n.cfg for n in nets), key=lambda c: c.in_features)

    def forward(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        answers = [net(points[..., : net.cfg.in_features]) for net in self.nets]
        keypoints = torch.stack([k for k, _ in answers]).mean(dim=0)
        seg = torch.stack([s for _, s in answers]).mean(dim=0)
        return keypoints, seg


class PointNetExport(nn.Module):
    """The exported form: segmentation as sigmoid scores."""

    def __init__(self, net: PointNet):
        super().__init__()
        self.net = net

    def forward(self, points):
        keypoints, seg_logits = self.net(points)
        return keypoints, torch.sigmoid(seg_logits)
