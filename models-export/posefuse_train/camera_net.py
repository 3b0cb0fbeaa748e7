"""Camera network: SimpleBaseline (a ResNet backbone of stride 32, stride-2 deconvolutions, a 1x1 conv
and a sigmoid) predicting K keypoint heatmaps. Three deconvolutions give heatmaps at a quarter of the
input resolution, as in the paper; a fourth, or a last conv whose 2x2 sub-cells a pixel shuffle lays
out (`final_shuffle`), gives half, which is how a small crop still gets a grid fine enough to tell
neighbouring LiDAR points apart (docs/TRAINING.md, "Heatmap resolution"). Each deconvolution can be
a 3x3 convolution and a pixel shuffle instead (`upsample = "shuffle"`), which INT8 kernels cover
(docs/TRAINING.md, "Upsampling")."""

from __future__ import annotations

import torch
from torch import nn

from .config import CameraNetConfig
from .keypoints import FLIP, K


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, cin: int, width: int, stride: int):
        super().__init__()
        cout = width * self.expansion
        self.conv1 = nn.Conv2d(cin, width, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.down = None
        if stride != 1 or cin != cout:
            self.down = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x):
        y = torch.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return torch.relu(y + (x if self.down is None else self.down(x)))


class Bottleneck(nn.Module):
    expansion = 4

    def __init__(self, cin: int, width: int, stride: int):
        super().__init__()
        cout = width * self.expansion
        self.conv1 = nn.Conv2d(cin, width, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, stride, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, cout, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(cout)
        self.down = None
        if stride != 1 or cin != cout:
            self.down = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x):
        y = torch.relu(self.bn1(self.conv1(x)))
        y = torch.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return torch.relu(y + (x if self.down is None else self.down(x)))


# name -> (block, blocks per stage, base width)
BACKBONES = {
    "resnet50": (Bottleneck, (3, 4, 6, 3), 64),
    "resnet18": (BasicBlock, (2, 2, 2, 2), 64),
    "resnet18-w32": (BasicBlock, (2, 2, 2, 2), 32),
    "resnet18-w16": (BasicBlock, (2, 2, 2, 2), 16),
}


class ResNet(nn.Module):
    """Plain ResNet trunk (stride BACKBONE_STRIDE), no classifier."""

    def __init__(self, name: str):
        super().__init__()
        block, depths, width = BACKBONES[name]
        self.stem = nn.Sequential(
            nn.Conv2d(3, width, 7, 2, 3, bias=False),
            nn.BatchNorm2d(width),
            nn.ReLU(inplace=True),
            nn.MaxPool2d(3, 2, 1),
        )
        stages, cin = [], width
        for i, n in enumerate(depths):
            w = width * 2**i
            blocks = []
            for b in range(n):
                blocks.append(block(cin, w, 2 if (b == 0 and i > 0) else 1))
                cin = w * block.expansion
            stages.append(nn.Sequential(*blocks))
        self.stages = nn.Sequential(*stages)
        self.out_channels = cin

    def forward(self, x):
        return self.stages(self.stem(x))


BACKBONE_STRIDE = 32


def predicted_heatmap_size(image_size: int, cfg: CameraNetConfig) -> int:
    """The side of the heatmaps the net predicts for an S x S crop."""
    return image_size * 2**cfg.deconv_layers * cfg.final_shuffle // BACKBONE_STRIDE


def deconv_layers_for(image_size: int, heatmap_size: int, final_shuffle: int = 1) -> int:
    """The number of deconvolutions that turn an S x S crop into H x H heatmaps."""
    for layers in range(1, 6):
        if image_size * 2**layers * final_shuffle == heatmap_size * BACKBONE_STRIDE:
            return layers
    raise ValueError(
        f"heatmap_size {heatmap_size} must be image_size {image_size} x {final_shuffle} / 2^k, k = 0..4 "
        f"(a stride-{BACKBONE_STRIDE} backbone and stride-2 deconvolutions)"
    )


def check_heatmap_size(image_size: int, heatmap_size: int, cfg: CameraNetConfig) -> None:
    """Refuses a pipeline whose heatmap_size is not what the camera net predicts."""
    if heatmap_size != predicted_heatmap_size(image_size, cfg):
        raise ValueError(
            f"heatmap_size {heatmap_size} is not what the camera net predicts for {image_size} px crops "
            f"with {cfg.deconv_layers} deconvolutions and final_shuffle {cfg.final_shuffle} "
            f"({predicted_heatmap_size(image_size, cfg)}); set deconv_layers "
            f"to {deconv_layers_for(image_size, heatmap_size, cfg.final_shuffle)}"
        )


def upsampling_stage(cin: int, cout: int, kind: str) -> list[nn.Module]:
    """One stride-2 upsampling stage. "shuffle" puts BatchNorm and ReLU before the pixel shuffle so
    that both fold into the convolution, leaving a graph of convolutions and one rearrangement."""
    if kind == "deconv":
        return [
            nn.ConvTranspose2d(cin, cout, 4, 2, 1, bias=False),
            nn.BatchNorm2d(cout),
            nn.ReLU(inplace=True),
        ]
    return [  # "shuffle" (CameraNetConfig admits no other kind)
        nn.Conv2d(cin, 4 * cout, 3, 1, 1, bias=False),
        nn.BatchNorm2d(4 * cout),
        nn.ReLU(inplace=True),
        nn.PixelShuffle(2),
    ]


class CameraNet(nn.Module):
    def __init__(self, cfg: CameraNetConfig):
        super().__init__()
        self.cfg = cfg
        self.backbone = ResNet(cfg.backbone)
        layers, cin = [], self.backbone.out_channels
        for _ in range(cfg.deconv_layers):
            layers += upsampling_stage(cin, cfg.deconv_channels, cfg.upsample)
            cin = cfg.deconv_channels
        self.deconv = nn.Sequential(*layers)
        self.final = nn.Conv2d(cin, K * cfg.final_shuffle**2, 1)
        self.shuffle = nn.PixelShuffle(cfg.final_shuffle) if cfg.final_shuffle > 1 else nn.Identity()
        self.facing = nn.Linear(self.backbone.out_channels, 1) if cfg.facing_head else None
        self._init()

    def _init(self):
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.ConvTranspose2d):
                nn.init.normal_(m.weight, std=0.001)
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
        nn.init.normal_(self.final.weight, std=0.001)
        # Targets are almost all zero: start the sigmoid near zero rather than at 0.5.
        nn.init.constant_(self.final.bias, -4.0)

    def logits(self, image: torch.Tensor) -> torch.Tensor:
        return self.shuffle(self.final(self.deconv(self.backbone(image))))

    def forward(self, image: torch.Tensor, with_facing: bool = False):
        """Heatmaps [B,K,H,W]; with `with_facing` (training) also the facing head's logit [B]."""
        if not with_facing:
            return torch.sigmoid(self.logits(image))
        if self.facing is None:
            raise ValueError("this camera net has no facing head")
        features = self.backbone(image)
        heatmaps = torch.sigmoid(self.shuffle(self.final(self.deconv(features))))
        return heatmaps, self.facing(features.mean(dim=(2, 3))).squeeze(1)


def as_served(net: CameraNet, flip_test: bool) -> CameraNet | FlipTest:
    """The net as the bundle will run it."""
    return FlipTest(net) if flip_test else net


class FlipTest(nn.Module):
    """A camera net asked twice, about the crop and about its mirror image, inside one graph: the
    mirror's heatmaps are flipped back, their left and right channels exchanged, and the two
    averaged (SimpleBaseline's flip test). The server runs it as any camera net; it costs a second
    pass of the backbone. docs/TRAINING.md, "Flip test".

    Heatmap cell j stands for model pixel j·S/W and mirroring maps pixel u to S − u, so the
    mirror's cell W − j lands on cell j: flipped back, the mirror's heatmaps move one cell right.
    Column 0 has no counterpart and keeps the plain pass's value."""

    def __init__(self, net: CameraNet):
        super().__init__()
        self.net = net
        self.register_buffer("swap", torch.tensor(FLIP), persistent=False)

    @property
    def cfg(self) -> CameraNetConfig:
        return self.net.cfg

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        b = image.shape[0]
        both = self.net(torch.cat([image, image.flip(3)], dim=0))
        plain, mirrored = both[:b], both[b:]
        back = mirrored.flip(3).index_select(1, self.swap)
        back = torch.cat([plain[..., :1], back[..., :-1]], dim=3)
        return 0.5 * (plain + back)
