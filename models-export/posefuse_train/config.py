"""Configurations as plain dataclasses.

`PipelineConfig` mirrors crates/core/src/pipeline/config.rs field for field: it is read from the training
data's dataset.json and copied verbatim into the bundle manifest, so the server pre-processes
exactly as the data was prepared.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

NOMINAL_LIDAR_ORIGIN = [1.43, 0.0, 2.12]


# The model's part of the preprocessing (a recipe's [pipeline] may set them); the rest is the data's.
MODEL_FIELDS = (
    "heatmap_size",
    "smoothing_kernel",
    "smoothing_sigma",
    "sampling",
    "lift_temperature",
    "min_points",
)


@dataclass
class PipelineConfig:
    image_size: int = 256
    crop_scale: float = 1.2
    mean: list[float] = field(default_factory=lambda: [0.485, 0.456, 0.406])
    std: list[float] = field(default_factory=lambda: [0.229, 0.224, 0.225])
    heatmap_size: int = 64
    smoothing_kernel: int = 7
    smoothing_sigma: float = 3.0
    # How a point reads its heatmap cell: "nearest" (the paper) or "bilinear" (sub-cell).
    sampling: str = "nearest"
    num_points: int = 256
    box_margin: float = 0.15
    rotate_by_heading: bool = True
    # The point networks' frame (crates/core/src/pipeline/config.rs `PointFrame`); None: after
    # rotate_by_heading.
    frame: str | None = None
    view_origin: list[float] = field(default_factory=lambda: list(NOMINAL_LIDAR_ORIGIN))
    lift_temperature: float = 2000.0
    min_points: int = 8

    @staticmethod
    def with_image_size(image_size: int) -> PipelineConfig:
        return PipelineConfig(image_size=image_size, heatmap_size=image_size // 4)

    @staticmethod
    def from_dict(d: dict) -> PipelineConfig:
        names = {f.name for f in dataclasses.fields(PipelineConfig)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown preprocessing keys: {sorted(unknown)}")
        return PipelineConfig(**d)

    def point_frame(self) -> str:
        """box_heading, view or centred, as the server reads it."""
        if self.frame is not None:
            return self.frame
        return "box_heading" if self.rotate_by_heading else "centred"

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        # Written as the server writes them: `frame` only for the view frame, `view_origin` only
        # when not the nominal one (crates/core/src/pipeline/config.rs).
        if d["frame"] is None:
            del d["frame"]
        if d["sampling"] == "nearest":
            del d["sampling"]
        if d["view_origin"] == NOMINAL_LIDAR_ORIGIN:
            del d["view_origin"]
        d["mean"] = [float(x) for x in d["mean"]]
        d["std"] = [float(x) for x in d["std"]]
        return d


UPSAMPLING = ("deconv", "shuffle")


@dataclass
class CameraNetConfig:
    backbone: str = "resnet18-w16"  # see camera_net.BACKBONES
    deconv_channels: int = 64
    deconv_layers: int = 3
    # > 1: the last 1x1 conv predicts final_shuffle² sub-cells per cell, rearranged into a grid that
    # much finer (sub-pixel convolution): a finer heatmap for the price of a wider 1x1 conv.
    final_shuffle: int = 1
    # How each stride-2 upsampling stage is made: "deconv" (a 4x4 transposed convolution, as the
    # paper's SimpleBaseline) or "shuffle" (a 3x3 convolution to 4x the channels and a pixel
    # shuffle), which ONNX Runtime's INT8 kernels cover (docs/TRAINING.md, "Upsampling").
    upsample: str = "deconv"
    # A training-only head on the pooled backbone features: does the person face the camera (from
    # the 2D labels' left and right)? Not exported; docs/TRAINING.md "Facing target".
    facing_head: bool = False

    def __post_init__(self):
        # refused here, so that a recipe fails when it loads rather than when the net is built
        if self.upsample not in UPSAMPLING:
            raise ValueError(f"upsample must be one of {UPSAMPLING}, not {self.upsample!r}")


@dataclass
class PointNetConfig:
    in_features: int = 3  # 3 (LiDAR-only) or 3 + K (fusion)
    # Narrower than the paper's 64-64-128-256-1024 so that five networks train within the CPU budget.
    local_channels: tuple[int, ...] = (32, 64)
    global_channels: tuple[int, ...] = (128, 256)
    head_channels: tuple[int, ...] = (256, 128)
    seg_channels: tuple[int, ...] = (64,)
