import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch
from test_export import small_models

from posefuse_train.config import PipelineConfig
from posefuse_train.export import camera_from_checkpoint, export_bundle, load_checkpoint
from tools import camera_from_bundle


def bundle_with_trained_statistics(path):
    """A bundle whose camera has BatchNorm statistics far from the identity, as a trained one has:
    folding them into the convolutions is then visible in the weights."""
    cfg = PipelineConfig.with_image_size(32)
    cfg.num_points = 64
    cam, fusion, lidar = small_models(cfg)
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for m in cam.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                n = m.num_features
                m.weight.copy_(0.5 + torch.rand(n, generator=g))
                m.bias.copy_(torch.randn(n, generator=g) * 0.2)
                m.running_mean.copy_(torch.randn(n, generator=g) * 0.2)
                m.running_var.copy_(0.5 + torch.rand(n, generator=g))
        # a head that reads its input (an untrained one outputs sigmoid(-4) everywhere)
        cam.final.weight.copy_(torch.randn(cam.final.weight.shape, generator=g) * 0.3)
    training = {"config": {"camera": {"backbone": "resnet18-w16", "deconv_channels": 16, "epochs": 3.0}}}
    export_bundle(path, cam, fusion, lidar, cfg, trained=True, training=training)
    return cam.eval()


def test_the_recovered_camera_gives_the_bundles_heatmaps(tmp_path):
    original = bundle_with_trained_statistics(tmp_path / "b")
    camera_from_bundle.main(["--bundle", str(tmp_path / "b"), "--out", str(tmp_path / "camera.pt")])
    ckpt = load_checkpoint(tmp_path / "camera.pt")
    assert ckpt["kind"] == "camera" and ckpt["train_config"]["epochs"] == 3.0
    assert ckpt["pipeline"]["image_size"] == 32
    net = camera_from_checkpoint(ckpt)
    x = torch.randn(4, 3, 32, 32, generator=torch.Generator().manual_seed(2))
    sess = ort.InferenceSession(str(tmp_path / "b" / "camera.onnx"), providers=["CPUExecutionProvider"])
    want = sess.run(None, {"image": x.numpy()})[0]
    with torch.no_grad():
        got, first = net(x).numpy(), original(x).numpy()
    assert np.abs(got - want).max() < 1e-5
    assert np.abs(got - first).max() < 1e-5
    # the statistics were not the identity: a net without them answers differently
    fresh = camera_from_bundle.CameraNet(net.cfg).eval()
    with torch.no_grad():
        assert np.abs(fresh(x).numpy() - want).max() > 1e-3


def test_a_manifest_naming_another_architecture_is_refused(tmp_path):
    bundle_with_trained_statistics(tmp_path / "b")
    path = tmp_path / "b" / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["training"]["config"]["camera"]["backbone"] = "resnet18-w32"
    path.write_text(json.dumps(manifest))
    with pytest.raises(SystemExit, match="not"):
        camera_from_bundle.main(["--bundle", str(tmp_path / "b"), "--out", str(tmp_path / "camera.pt")])
    assert not (tmp_path / "camera.pt").exists()


def test_the_committed_default_bundles_camera_comes_back(tmp_path):
    """The default bundle's camera upsamples by pixel shuffle and runs the flip test inside its
    graph: the recovered net, asked as the bundle asks it, gives its heatmaps (the tool checks
    that against ONNX Runtime before it writes), and the checkpoint keeps the architecture."""
    default = Path(__file__).resolve().parents[2] / "models" / "default"
    camera_from_bundle.main(["--bundle", str(default), "--out", str(tmp_path / "camera.pt")])
    net = camera_from_checkpoint(load_checkpoint(tmp_path / "camera.pt"))
    manifest = json.loads((default / "manifest.json").read_text())
    assert net.cfg.upsample == manifest["training"]["config"]["camera"]["upsample"] == "shuffle"
    assert manifest["models"]["camera"]["flip_test"]
    x = torch.randn(2, 3, 128, 128, generator=torch.Generator().manual_seed(3))
    sess = ort.InferenceSession(str(default / "camera.onnx"), providers=["CPUExecutionProvider"])
    want = sess.run(None, {"image": x.numpy()})[0]
    with torch.no_grad():
        plain = net(x).numpy()
        flipped = camera_from_bundle.as_served(net, True)(x).numpy()
    assert np.abs(flipped - want).max() < 1e-4
    assert np.abs(plain - want).max() > 1e-3  # the graph's answer is the flip test's, not one pass
