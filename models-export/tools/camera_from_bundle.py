"""A trained camera net back from a bundle's camera.onnx, as a checkpoint the trainer reuses
(`python -m experiments.ablation --camera-checkpoint`): new point-net rows can then be trained
behind a bundle's camera without retraining it.

    python -m tools.camera_from_bundle --bundle ../models/default --out runs/default_camera.pt

The export folds each backbone BatchNorm into the convolution before it; the folded weights go
back into the convolution and the BatchNorm becomes the identity plus the folded bias. The
recovered net is checked against ONNX Runtime on random crops before it is written.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnx import numpy_helper
from torch import nn

from posefuse_train.camera_net import CameraNet, as_served, deconv_layers_for
from posefuse_train.config import CameraNetConfig, PipelineConfig
from posefuse_train.train import TrainCameraConfig, checkpoint


def conv_bn_pairs(net: CameraNet) -> list[tuple[nn.Conv2d, nn.BatchNorm2d | None]]:
    """The net's Conv2d layers in forward order, each with the BatchNorm that follows it."""
    order: list[nn.Module] = []
    convs = [m for m in net.modules() if isinstance(m, nn.Conv2d)]
    hooks = [m.register_forward_pre_hook(lambda m, _: order.append(m)) for m in convs]
    with torch.no_grad():
        net.eval()(torch.zeros(1, 3, 64, 64))
    for h in hooks:
        h.remove()
    bn_after = {}
    for mod in net.modules():
        children = list(mod.named_children())
        for (_, a), (_, b) in zip(children, children[1:], strict=False):
            if isinstance(a, nn.Conv2d) and isinstance(b, nn.BatchNorm2d):
                bn_after[a] = b
        for name, child in children:
            if isinstance(child, nn.Conv2d) and name.startswith("conv"):
                bn = getattr(mod, "bn" + name[4:], None)
                if isinstance(bn, nn.BatchNorm2d):
                    bn_after[child] = bn
    return [(c, bn_after.get(c)) for c in order]


def load_camera(model_path: Path, cfg: CameraNetConfig) -> CameraNet:
    """A CameraNet of architecture `cfg` holding the weights of `model_path`."""
    model = onnx.load(str(model_path))
    init = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    net = CameraNet(cfg)
    named = dict(net.state_dict())
    # the deconvolutions and the head keep their names; their BatchNorms are not folded
    for k in list(named):
        if k in init:
            if tuple(init[k].shape) != tuple(named[k].shape):
                raise SystemExit(f"{model_path}: {k} is {init[k].shape}, not {tuple(named[k].shape)}")
            named[k] = torch.from_numpy(init[k].copy())
    net.load_state_dict(named)
    convs = [n for n in model.graph.node if n.op_type == "Conv"]
    pairs = conv_bn_pairs(net)
    if len(convs) != len(pairs):
        raise SystemExit(f"{model_path}: {len(convs)} Conv nodes, the architecture has {len(pairs)}")
    with torch.no_grad():
        for node, (conv, bn) in zip(convs, pairs, strict=True):
            w = torch.from_numpy(init[node.input[1]].copy())
            if w.shape != conv.weight.shape:
                want = tuple(conv.weight.shape)
                raise SystemExit(f"{model_path}: {node.input[1]} is {tuple(w.shape)}, not {want}")
            conv.weight.copy_(w)
            b = torch.from_numpy(init[node.input[2]].copy()) if len(node.input) > 2 else None
            if bn is None:
                if conv.bias is not None and b is not None:
                    conv.bias.copy_(b)
                continue
            bn.weight.fill_(1.0)
            bn.bias.copy_(b if b is not None else torch.zeros_like(bn.bias))
            bn.running_mean.zero_()
            bn.running_var.fill_(1.0 - bn.eps)
    return net.eval()


def max_difference(net: nn.Module, model_path: Path, size: int, n: int = 8) -> float:
    x = torch.randn(n, 3, size, size, generator=torch.Generator().manual_seed(0))
    sess = ort.InferenceSession(str(model_path), providers=["CPUExecutionProvider"])
    want = sess.run(None, {sess.get_inputs()[0].name: x.numpy()})[0]
    with torch.no_grad():
        got = net(x).numpy()
    return float(np.abs(got - want).max())


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m tools.camera_from_bundle", description=__doc__.split("\n")[0])
    p.add_argument("--bundle", required=True, help="bundle directory (manifest.json + camera.onnx)")
    p.add_argument("--out", required=True, help="checkpoint to write (.pt)")
    p.add_argument("--tol", type=float, default=1e-4, help="largest heatmap difference to ONNX Runtime")
    a = p.parse_args(argv)
    bundle = Path(a.bundle)
    manifest = json.loads((bundle / "manifest.json").read_text())
    pipeline = PipelineConfig.from_dict(manifest["preprocessing"])
    cam = manifest["training"]["config"]["camera"]
    shuffle = cam.get("final_shuffle", 1)
    net_cfg = CameraNetConfig(
        backbone=cam["backbone"],
        deconv_channels=cam["deconv_channels"],
        deconv_layers=deconv_layers_for(pipeline.image_size, pipeline.heatmap_size, shuffle),
        final_shuffle=shuffle,
        upsample=cam.get("upsample", CameraNetConfig.upsample),
    )
    model_path = bundle / manifest["models"]["camera"]["file"]
    net = load_camera(model_path, net_cfg)
    # a flip-test graph runs the same convolutions on the crop and its mirror as one batch
    served = as_served(net, manifest["models"]["camera"].get("flip_test", False))
    diff = max_difference(served, model_path, pipeline.image_size)
    if diff > a.tol:
        raise SystemExit(f"recovered camera net differs from {model_path} by {diff:.2e} (> {a.tol})")
    fields = TrainCameraConfig.__dataclass_fields__
    kept = {k: tuple(v) if isinstance(v, list) else v for k, v in cam.items() if k in fields}
    train_cfg = TrainCameraConfig(**kept)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    torch.save(checkpoint(net, pipeline, train_cfg, f"{bundle}/camera.onnx"), a.out)
    print(f"{a.out}: camera {net_cfg.backbone} from {model_path}, max |Δ| {diff:.2e} against ONNX Runtime")


if __name__ == "__main__":
    main()
