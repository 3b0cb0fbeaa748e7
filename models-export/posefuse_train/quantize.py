"""INT8 camera network: static quantization of a bundle's `camera.onnx` with ONNX Runtime's
quantizer, calibrated on simulated crops, written beside it as `camera_int8.onnx` and declared in
the manifest as `models.camera.variants.int8` (docs/BUNDLE.md, "Precision").

The default format is ONNX Runtime's QOperator (QLinearConv and friends): on the x86 CPU it was
measured on, the QDQ form of the same quantization ran no faster than float32 (`--format qdq`
keeps it, e.g. for execution providers that want QDQ graphs).

    python -m posefuse_train.quantize --bundle models/default --calibration data/street_calib

The calibration crops should come from the training distribution (a `posefuse simulate` run with
the training set's profile and seed), never from the held-out set. The point networks stay in
float32: they are a small share of a request's time. `--default` also sets the manifest's
`precision` to int8, which the server then serves unless `--precision fp32` is given.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from onnxruntime.quantization import (
    CalibrationDataReader,
    CalibrationMethod,
    QuantFormat,
    QuantType,
    quantize_static,
)
from onnxruntime.quantization.shape_inference import quant_pre_process

from .bundle_eval import normalize
from .config import PipelineConfig
from .shards import ShardSet

VARIANT = "int8"
FILE = "camera_int8.onnx"
FORMATS = {"qoperator": QuantFormat.QOperator, "qdq": QuantFormat.QDQ}
METHODS = {
    "percentile": CalibrationMethod.Percentile,
    "entropy": CalibrationMethod.Entropy,
    "minmax": CalibrationMethod.MinMax,
}


class Crops(CalibrationDataReader):
    """Normalized crops, `batch` at a time, as the server feeds the camera network."""

    def __init__(self, images: np.ndarray, batch: int = 32):
        self.images, self.batch, self.at = images, batch, 0

    def get_next(self):
        if self.at >= len(self.images):
            return None
        x = self.images[self.at : self.at + self.batch]
        self.at += self.batch
        return {"image": x}


def calibration_crops(shards: ShardSet, cfg: PipelineConfig, count: int) -> np.ndarray:
    """The first `count` crops of a shard set, normalized [n,3,S,S] float32."""
    parts, have = [], 0
    for i in range(shards.num_shards):
        img = shards.read(i, ("image",))["image"][: count - have]
        parts.append(img)
        have += len(img)
        if have >= count:
            break
    images = np.concatenate(parts, axis=0)
    if images.shape[1] != cfg.image_size:
        raise SystemExit(f"calibration crops are {images.shape[1]} px, the camera takes {cfg.image_size}")
    return normalize(images, cfg)


def quantize_camera(
    bundle: Path, calibration: Path, count: int = 512, method: str = "percentile", fmt: str = "qoperator"
) -> dict:
    """Writes `bundle/camera_int8.onnx` and returns its manifest entry."""
    manifest = json.loads((bundle / "manifest.json").read_text())
    cfg = PipelineConfig.from_dict(manifest["preprocessing"])
    shards = ShardSet(calibration)
    crops = calibration_crops(shards, cfg, count)
    out = bundle / FILE
    with tempfile.TemporaryDirectory() as tmp:
        # shape inference and BatchNorm folding first, as ONNX Runtime's quantizer asks
        pre = Path(tmp) / "camera_pre.onnx"
        quant_pre_process(str(bundle / manifest["models"]["camera"]["file"]), str(pre))
        quantize_static(
            str(pre),
            str(out),
            Crops(crops),
            quant_format=FORMATS[fmt],
            per_channel=True,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
            calibrate_method=METHODS[method],
        )
    return {
        "file": FILE,
        "sha256": hashlib.sha256(out.read_bytes()).hexdigest(),
        "calibration": {
            "data": {k: shards.meta.get(k) for k in ("profile", "seed", "count", "version")},
            "crops": int(len(crops)),
            "method": method,
        },
        "format": fmt,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m posefuse_train.quantize", description=__doc__.split("\n")[0])
    ap.add_argument("--bundle", required=True, type=Path)
    ap.add_argument("--calibration", required=True, type=Path, help="shards from the training distribution")
    ap.add_argument("--count", type=int, default=512, help="calibration crops")
    ap.add_argument("--method", choices=sorted(METHODS), default="percentile")
    ap.add_argument("--format", choices=sorted(FORMATS), default="qoperator")
    ap.add_argument("--default", action="store_true", help="serve INT8 unless --precision fp32 is asked")
    a = ap.parse_args(argv)
    entry = quantize_camera(a.bundle, a.calibration, a.count, a.method, a.format)
    path = a.bundle / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["models"]["camera"].setdefault("variants", {})[VARIANT] = entry
    if a.default:
        manifest["precision"] = VARIANT
    path.write_text(json.dumps(manifest, indent=2) + "\n")
    print(f"wrote {a.bundle / FILE} ({entry['calibration']['crops']} calibration crops, {a.method})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
