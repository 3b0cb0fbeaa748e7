import json
import math

import numpy as np
import onnxruntime as ort
import pytest
import torch
from test_export import small_models
from torch import nn

from posefuse_train.config import PipelineConfig, PointNetConfig
from posefuse_train.export import export_bundle, main
from posefuse_train.facing_net import FacingPointNet, facing_cos_sin, turn
from posefuse_train.keypoints import NAMES, K
from posefuse_train.point_net import PointNet

SMALL = dict(local_channels=(16,), global_channels=(32,), head_channels=(32,), seg_channels=(16,))


def body(yaw: float) -> torch.Tensor:
    """[1,K,3]: shoulders 0.4 m and hips 0.3 m apart, facing `yaw` (as facing.rs's tests build it)."""
    left = (-math.sin(yaw), math.cos(yaw))
    kp = torch.zeros(1, K, 3)
    for name, width, z, side in (
        ("left_shoulder", 0.4, 1.4, 1),
        ("right_shoulder", 0.4, 1.4, -1),
        ("left_hip", 0.3, 0.9, 1),
        ("right_hip", 0.3, 0.9, -1),
    ):
        kp[0, NAMES.index(name)] = torch.tensor([side * left[0] * width / 2, side * left[1] * width / 2, z])
    return kp


def yaw_of(cos: torch.Tensor, sin: torch.Tensor) -> float:
    return math.atan2(float(sin), float(cos))


def yaw_gap(a: float, b: float) -> float:
    d = (a - b) % (2 * math.pi)
    return min(d, 2 * math.pi - d)


@pytest.mark.parametrize("yaw", [0.0, 0.7, math.pi / 2, 2.5, -1.2, -math.pi / 2])
def test_the_facing_is_the_servers(yaw):
    assert yaw_gap(yaw_of(*facing_cos_sin(body(yaw))), yaw) < 1e-6
    # a person whose left is +y faces +x
    assert facing_cos_sin(body(0.0))[0].item() == pytest.approx(1.0)


def test_exchanged_sides_face_the_other_way_and_cancelling_pairs_do_not_turn():
    kp = body(0.3)
    sw = kp.clone()
    for a, b in (("left_shoulder", "right_shoulder"), ("left_hip", "right_hip")):
        sw[0, NAMES.index(a)], sw[0, NAMES.index(b)] = kp[0, NAMES.index(b)], kp[0, NAMES.index(a)]
    assert yaw_gap(yaw_of(*facing_cos_sin(sw)), 0.3 + math.pi) < 1e-6
    nowhere = torch.zeros(1, K, 3)
    cos, sin = facing_cos_sin(nowhere)
    assert (cos.item(), sin.item()) == (1.0, 0.0)


def test_turn_rotates_counter_clockwise_about_z():
    xyz = torch.tensor([[[1.0, 0.0, 0.5], [0.0, 2.0, -1.0]]])
    out = turn(xyz, torch.tensor([0.0]), torch.tensor([1.0]))
    assert torch.allclose(out, torch.tensor([[[0.0, 1.0, 0.5], [-2.0, 0.0, -1.0]]]), atol=1e-7)


class MeanDirection(nn.Module):
    """A facing net that turns with its input: the body faces the points' mean horizontal direction."""

    def __init__(self, in_features: int):
        super().__init__()
        self.cfg = PointNetConfig(in_features=in_features, **SMALL)

    def forward(self, points):
        m = points[..., :2].mean(dim=1)
        yaw = torch.atan2(m[:, 1], m[:, 0])
        kp = torch.cat([body(float(y)) for y in yaw])
        return kp, torch.zeros(points.shape[0], points.shape[1], K)


def points(b=3, n=64, c=3 + K, seed=0, spread=0.4):
    g = torch.Generator().manual_seed(seed)
    xyz = torch.randn(b, n, 3, generator=g) * spread + torch.tensor([0.3, 0.0, 0.0])
    return torch.cat([xyz, torch.rand(b, n, c - 3, generator=g)], dim=2)


def turned(p: torch.Tensor, angle: float) -> torch.Tensor:
    b = p.shape[0]
    xyz = turn(p[..., :3], torch.full((b,), math.cos(angle)), torch.full((b,), math.sin(angle)))
    return torch.cat([xyz, p[..., 3:]], dim=2)


@pytest.mark.parametrize("passes", [0, 2])
def test_the_answer_turns_with_the_input_whatever_the_second_net(passes):
    """The second net only ever sees the body facing +x, so the heading the box was given cannot
    move the answer: it turns with the points (given a first net that does)."""
    torch.manual_seed(1)
    second = PointNet(PointNetConfig(in_features=3 + K, **SMALL)).eval()
    net = FacingPointNet(MeanDirection(3 + K), second, passes=passes).eval()
    p = points()
    with torch.no_grad():
        kp, seg = net(p)
        for angle in (0.4, math.pi / 2, 2.9, -2.0):
            kp_t, seg_t = net(turned(p, angle))
            c, s = torch.full((3,), math.cos(angle)), torch.full((3,), math.sin(angle))
            assert torch.allclose(kp_t, turn(kp, c, s), atol=1e-4), angle
            assert torch.allclose(seg_t, seg, atol=1e-4)
    # the second net alone does not turn with its input: the property is the composite's
    with torch.no_grad():
        alone, _ = second(turned(p, 2.0))
        c, s = torch.full((3,), math.cos(2.0)), torch.full((3,), math.sin(2.0))
        assert not torch.allclose(alone, turn(second(p)[0], c, s), atol=1e-2)


def test_four_turns_make_any_first_net_blind_to_quarter_turns():
    torch.manual_seed(2)
    first = PointNet(PointNetConfig(in_features=3, **SMALL)).eval()
    second = PointNet(PointNetConfig(in_features=3, **SMALL)).eval()
    p = points(c=3)
    four = FacingPointNet(first, second, turns=4).eval()
    with torch.no_grad():
        cos, sin = four.first_facing(p[..., :3], p[..., 3:])
        cos_q, sin_q = four.first_facing(turned(p, math.pi / 2)[..., :3], p[..., 3:])
        assert torch.allclose(cos_q, -sin, atol=1e-5) and torch.allclose(sin_q, cos, atol=1e-5)
        one = FacingPointNet(first, second, turns=1).eval()
        cos1, sin1 = one.first_facing(turned(p, math.pi / 2)[..., :3], p[..., 3:])
        assert not (torch.allclose(cos1, -sin, atol=1e-3) and torch.allclose(sin1, cos, atol=1e-3))


def test_a_box_heading_the_first_net_agrees_with_is_kept():
    torch.manual_seed(3)
    second = PointNet(PointNetConfig(in_features=3 + K, **SMALL)).eval()
    p = points(b=2, spread=0.05)
    # the first net says: the first person faces 10° off the box heading, the second 60°
    p = torch.stack([turned(p[:1], math.radians(10))[0], turned(p[1:], math.radians(60))[0]])
    net = FacingPointNet(MeanDirection(3 + K), second, passes=1, agree_deg=30).eval()
    never = FacingPointNet(MeanDirection(3 + K), second, passes=1).eval()
    with torch.no_grad():
        first_yaws = [yaw_of(c, s) for c, s in zip(*net.first_facing(p[..., :3], p[..., 3:]), strict=True)]
        assert abs(math.degrees(first_yaws[0])) < 30 < abs(math.degrees(first_yaws[1]))
        kp, _ = net(p)
        as_given, _ = second(p)
        turned_kp, _ = never(p)
    assert torch.allclose(kp[0], as_given[0]) and not torch.allclose(kp[0], turned_kp[0], atol=1e-3)
    assert torch.allclose(kp[1], turned_kp[1]) and not torch.allclose(kp[1], as_given[1], atol=1e-3)


def test_nets_that_take_different_points_are_refused():
    a = PointNet(PointNetConfig(in_features=3, **SMALL))
    b = PointNet(PointNetConfig(in_features=3 + K, **SMALL))
    with pytest.raises(ValueError):
        FacingPointNet(a, b)
    with pytest.raises(ValueError):
        FacingPointNet(a, a, turns=0)


def test_a_bundle_with_the_facing_inside_exports_as_ordinary_point_nets(tmp_path):
    cfg = PipelineConfig.with_image_size(32)
    cfg.num_points = 64
    cam, fusion, lidar = small_models(cfg)
    first_f = PointNet(PointNetConfig(in_features=3 + K, **SMALL))
    first_l = PointNet(PointNetConfig(in_features=3, **SMALL))
    manifest = export_bundle(
        tmp_path / "b",
        cam,
        FacingPointNet(first_f, fusion, passes=1, turns=4, agree_deg=30),
        FacingPointNet(first_l, lidar, passes=1, turns=4),
        cfg,
        trained=False,
    )
    for key, c in (("point_fusion", 3 + K), ("point_lidar", 3)):
        m = manifest["models"][key]
        assert m["inputs"] == {"points": [-1, 64, c]}
        assert m["outputs"] == {"keypoints": [-1, K, 3], "segmentation": [-1, 64, K]}
        assert manifest["training"]["config"]["onnx_parity_max_abs_diff"][key] <= 1e-4
        sess = ort.InferenceSession(str(tmp_path / "b" / m["file"]), providers=["CPUExecutionProvider"])
        outs = sess.run(None, {"points": np.zeros((5, 64, c), np.float32)})
        assert [o.shape for o in outs] == [(5, K, 3), (5, 64, K)]


def test_cli_puts_the_facing_nets_in_front(tmp_path):
    torch.manual_seed(4)
    cfg = PipelineConfig.with_image_size(32)
    cfg.num_points = 64
    cam, fusion, lidar = small_models(cfg)
    paths = {}
    for name, net in (("fusion", fusion), ("lidar", lidar), ("first_f", fusion), ("first_l", lidar)):
        paths[name] = tmp_path / f"{name}.pt"
        train_config = {"rotate_deg": 180.0 if "first" in name else 20.0}
        ckpt = {"config": net.cfg.__dict__, "state_dict": net.state_dict(), "train_config": train_config}
        torch.save(ckpt, paths[name])
    paths["camera"] = tmp_path / "camera.pt"
    camera = {"config": cam.cfg.__dict__, "state_dict": cam.state_dict(), "pipeline": cfg.to_dict()}
    torch.save(camera, paths["camera"])
    common = ["--camera", str(paths["camera"])]
    common += ["--fusion", str(paths["fusion"]), "--lidar", str(paths["lidar"])]
    with pytest.raises(SystemExit):
        main([*common, "--facing-fusion", str(paths["first_f"]), "--out", str(tmp_path / "x")])
    facing_args = ["--facing-fusion", str(paths["first_f"]), "--facing-lidar", str(paths["first_l"])]
    shape = ["--facing-passes", "2", "--facing-turns", "4", "--facing-agree-deg", "30"]
    main([*common, *facing_args, *shape, "--out", str(tmp_path / "b")])
    manifest = json.loads((tmp_path / "b" / "manifest.json").read_text())
    facing = manifest["training"]["config"]["facing"]
    assert facing["passes"] == 2 and facing["turns"] == 4 and facing["agree_deg"] == 30.0
    assert facing["fusion"] == {"rotate_deg": 180.0}
    # the exported point nets are the composites: not the second net alone
    sess = ort.InferenceSession(str(tmp_path / "b" / "point_lidar.onnx"), providers=["CPUExecutionProvider"])
    p = points(b=2, c=3).numpy()
    got = sess.run(None, {"points": p})[0]
    with torch.no_grad():
        alone = lidar.eval()(torch.from_numpy(p))[0].numpy()
    assert not np.allclose(got, alone, atol=1e-3)


class Constant(nn.Module):
    """A second net that always answers a body facing `yaw` in its own input frame."""

    def __init__(self, yaw: float, in_features: int):
        super().__init__()
        self.yaw = yaw
        self.cfg = PointNetConfig(in_features=in_features, **SMALL)

    def forward(self, points):
        return body(self.yaw).repeat(points.shape[0], 1, 1), torch.zeros(points.shape[0], points.shape[1], K)


@pytest.mark.parametrize("passes", [0, 1, 3])
def test_each_pass_turns_the_points_by_the_facing_the_last_answer_had(passes):
    """The first net says 30°; a second net that always answers 20° off its input frame moves the
    frame by 20° per pass, and its last answer, turned back, faces 30° + 20° × (passes + 1)."""
    first, second = Constant(math.radians(30), 3 + K), Constant(math.radians(20), 3 + K)
    net = FacingPointNet(first, second, passes=passes).eval()
    p = points(b=1)
    with torch.no_grad():
        kp, _ = net(p)
    want = math.radians(30 + 20 * (passes + 1))
    assert yaw_gap(yaw_of(*facing_cos_sin(kp)), want) < math.radians(0.5)
