"""posefuse_train.quantize: an INT8 camera variant beside the float32 network, declared in the
manifest, close to it on calibration-like crops, and picked by `precision`."""

import hashlib
import json

import numpy as np
import onnx
import pytest
import torch
from test_export import small_models

from posefuse_train import quantize
from posefuse_train.bundle_eval import held_out, normalize, sessions
from posefuse_train.camera_net import CameraNet
from posefuse_train.config import CameraNetConfig
from posefuse_train.data import read_meta
from posefuse_train.export import export_bundle
from posefuse_train.shards import ShardSet


def test_the_int8_variant_is_declared_close_and_served_by_precision(synthetic_sets, tmp_path):
    _, cfg = read_meta(synthetic_sets[0])
    bundle = tmp_path / "b"
    cam, fusion, lidar = small_models(cfg)
    torch.manual_seed(1)
    with torch.no_grad():  # an untrained head answers a constant; give the net something to say
        for p in cam.parameters():
            p.add_(0.1 * torch.randn_like(p))
    export_bundle(bundle, cam, fusion, lidar, cfg, trained=False)
    args = ["--bundle", str(bundle), "--calibration", str(synthetic_sets[0]), "--count", "64"]
    assert quantize.main(args) == 0
    m = json.loads((bundle / "manifest.json").read_text())
    v = m["models"]["camera"]["variants"]["int8"]
    assert v["file"] == "camera_int8.onnx" and v["calibration"]["crops"] == 64
    assert v["sha256"] == hashlib.sha256((bundle / v["file"]).read_bytes()).hexdigest()
    assert "precision" not in m, "INT8 is served only when asked for, unless --default"
    ops = {n.op_type for n in onnx.load(str(bundle / v["file"])).graph.node}
    assert v["format"] == "qoperator" and "QLinearConv" in ops
    # the held-out crops through both: the INT8 heatmaps follow the float32 ones
    x = normalize(ShardSet(synthetic_sets[1]).read(0, ("image",))["image"][:16], cfg)
    (h32,) = sessions(bundle)["camera"].run(None, {"image": x})
    (h8,) = sessions(bundle, precision="int8")["camera"].run(None, {"image": x})
    assert not np.array_equal(h32, h8)
    assert np.abs(h8 - h32).mean() < 0.05 * np.abs(h32).max()
    assert np.corrcoef(h8.ravel(), h32.ravel())[0, 1] > 0.99
    # the point networks have no variant: int8 changes the camera only
    r32 = held_out(bundle, ShardSet(synthetic_sets[1]))
    r8 = held_out(bundle, ShardSet(synthetic_sets[1]), precision="int8")
    assert r8["lidar"] == r32["lidar"] and r8["camera"] != r32["camera"]
    with pytest.raises(SystemExit, match="no fp16 variant"):
        sessions(bundle, precision="fp16")
    # --default makes INT8 the bundle's own precision, which evaluation then runs unless asked
    quantize.main([*args, "--default"])
    assert json.loads((bundle / "manifest.json").read_text())["precision"] == "int8"
    (d8,) = sessions(bundle)["camera"].run(None, {"image": x})
    (d32,) = sessions(bundle, precision="fp32")["camera"].run(None, {"image": x})
    assert np.array_equal(d32, h32) and not np.array_equal(d8, h32)
    assert held_out(bundle, ShardSet(synthetic_sets[1]))["camera"] != r32["camera"]


@pytest.mark.parametrize(("upsample", "float_ops"), [("deconv", {"ConvTranspose"}), ("shuffle", set())])
def test_only_a_shuffle_upsampled_camera_quantizes_every_conv(synthetic_sets, tmp_path, upsample, float_ops):
    """docs/TRAINING.md, "Upsampling": ONNX Runtime has no INT8 transposed convolution, so a
    deconvolution head stays float32 between a dequantize and a quantize; sub-pixel stages leave
    no float convolution and only the pixel shuffle itself outside INT8."""
    _, cfg = read_meta(synthetic_sets[0])
    bundle = tmp_path / upsample
    _, fusion, lidar = small_models(cfg)
    torch.manual_seed(1)
    cam = CameraNet(CameraNetConfig(backbone="resnet18-w16", deconv_channels=16, upsample=upsample))
    with torch.no_grad():
        for p in cam.parameters():
            p.add_(0.1 * torch.randn_like(p))
    export_bundle(bundle, cam, fusion, lidar, cfg, trained=False)
    quantize.quantize_camera(bundle, synthetic_sets[0], count=64)
    ops = [n.op_type for n in onnx.load(str(bundle / quantize.FILE)).graph.node]
    assert {"Conv", "ConvTranspose"} & set(ops) == float_ops
    assert ops.count("QLinearConv") == sum(isinstance(m, torch.nn.Conv2d) for m in cam.modules())
    assert ops.count("DepthToSpace") == (3 if upsample == "shuffle" else 0)
