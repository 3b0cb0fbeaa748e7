import hashlib
import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

import posefuse_train
from posefuse_train.camera_net import FlipTest
from posefuse_train.config import CameraNetConfig, PipelineConfig, PointNetConfig
from posefuse_train.export import ParityError, check_parity, export_bundle, export_onnx, untrained_models
from posefuse_train.keypoints import FLIP, NAMES, WAYMO_TYPES, K
from posefuse_train.point_net import Blend, PointNet

PREPROCESSING_KEYS = {
    "image_size",
    "crop_scale",
    "mean",
    "std",
    "heatmap_size",
    "smoothing_kernel",
    "smoothing_sigma",
    "num_points",
    "box_margin",
    "rotate_by_heading",
    "lift_temperature",
    "min_points",
}


def small_models(cfg):
    torch.manual_seed(0)
    cam, _, _ = untrained_models(cfg, CameraNetConfig(backbone="resnet18-w16", deconv_channels=16))
    small = dict(local_channels=(16,), global_channels=(32,), head_channels=(32,), seg_channels=(16,))
    return (
        cam,
        PointNet(PointNetConfig(in_features=3 + K, **small)),
        PointNet(PointNetConfig(in_features=3, **small)),
    )


def test_bundle_manifest_hashes_shapes_and_runtime_parity(tmp_path):
    cfg = PipelineConfig.with_image_size(32)
    cfg.num_points = 64
    manifest = export_bundle(tmp_path / "b", *small_models(cfg), cfg, trained=False)
    on_disk = json.loads((tmp_path / "b" / "manifest.json").read_text())
    assert on_disk == manifest
    assert manifest["format_version"] == 1 and manifest["training"]["trained"] is False
    assert manifest["keypoints"] == {"names": NAMES, "waymo_types": WAYMO_TYPES}
    assert set(manifest["preprocessing"]) == PREPROCESSING_KEYS
    assert (
        manifest["preprocessing"]["lift_temperature"] == 2000.0
        and manifest["preprocessing"]["heatmap_size"] == 8
    )
    want = {
        "camera": ({"image": [-1, 3, 32, 32]}, {"heatmaps": [-1, K, 8, 8]}),
        "point_fusion": ({"points": [-1, 64, 3 + K]}, {"keypoints": [-1, K, 3], "segmentation": [-1, 64, K]}),
        "point_lidar": ({"points": [-1, 64, 3]}, {"keypoints": [-1, K, 3], "segmentation": [-1, 64, K]}),
    }
    for key, (inputs, outputs) in want.items():
        m = manifest["models"][key]
        path = tmp_path / "b" / m["file"]
        assert m["inputs"] == inputs and m["outputs"] == outputs
        assert m["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
        model = onnx.load(str(path))
        assert model.opset_import[0].version >= 17
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        assert [i.name for i in sess.get_inputs()] == list(inputs)
        assert [o.name for o in sess.get_outputs()] == list(outputs)
        # dynamic batch: a batch of 5 runs and gives 5 rows
        shape = [5 if d == -1 else d for d in next(iter(inputs.values()))]
        outs = sess.run(None, {next(iter(inputs)): np.zeros(shape, np.float32)})
        assert all(o.shape[0] == 5 for o in outs)
        assert manifest["training"]["config"]["onnx_parity_max_abs_diff"][key] <= 1e-4


def test_a_model_that_disagrees_with_its_onnx_file_is_refused(tmp_path):
    cfg = PipelineConfig.with_image_size(32)
    _, _, lidar = small_models(cfg)
    lidar.eval()
    x = torch.randn(1, 64, 3)
    export_onnx(lidar, x, tmp_path / "p.onnx", "points", ["keypoints", "segmentation"])
    assert check_parity(lidar, tmp_path / "p.onnx", lambda b: torch.randn(b, 64, 3), 1e-4) <= 1e-4
    with torch.no_grad():
        lidar.head_out.bias += 0.01
    with pytest.raises(ParityError):
        check_parity(lidar, tmp_path / "p.onnx", lambda b: torch.randn(b, 64, 3), 1e-4)


def test_cli_writes_an_untrained_bundle(tmp_path, capsys):
    from posefuse_train.export import main

    main(["--untrained", "--out", str(tmp_path / "u"), "--image-size", "32", "--backbone", "resnet18-w16"])
    m = json.loads((tmp_path / "u" / "manifest.json").read_text())
    assert m["version"] == posefuse_train.__version__
    assert m["preprocessing"]["image_size"] == 32 and m["models"]["camera"]["outputs"]["heatmaps"] == [
        -1,
        K,
        8,
        8,
    ]
    total = sum((tmp_path / "u" / v["file"]).stat().st_size for v in m["models"].values())
    assert total < 30e6


def test_cli_sets_the_bundle_version(tmp_path):
    from posefuse_train.export import main

    out = tmp_path / "v"
    main(
        [
            "--untrained",
            "--out",
            str(out),
            "--image-size",
            "32",
            "--backbone",
            "resnet18-w16",
            "--version",
            "7.1.2",
        ]
    )
    assert json.loads((out / "manifest.json").read_text())["version"] == "7.1.2"


@pytest.mark.parametrize("shuffle", [1, 2])
def test_cli_writes_a_bundle_with_half_resolution_heatmaps(tmp_path, shuffle):
    from posefuse_train.export import main

    out = tmp_path / f"h{shuffle}"
    args = ["--untrained", "--out", str(out), "--image-size", "32", "--heatmap-size", "16"]
    main([*args, "--final-shuffle", str(shuffle), "--backbone", "resnet18-w16"])
    m = json.loads((out / "manifest.json").read_text())
    assert m["preprocessing"]["heatmap_size"] == 16
    assert m["models"]["camera"]["outputs"]["heatmaps"] == [-1, K, 16, 16]
    sess = ort.InferenceSession(str(out / m["models"]["camera"]["file"]), providers=["CPUExecutionProvider"])
    assert sess.run(None, {"image": np.zeros((2, 3, 32, 32), np.float32)})[0].shape == (2, K, 16, 16)


def test_a_pipeline_whose_heatmaps_the_camera_does_not_predict_is_refused(tmp_path):
    cfg = PipelineConfig.with_image_size(32)
    cfg.heatmap_size = 16  # the small camera net predicts S/4 = 8
    with pytest.raises(ValueError, match="deconv_layers to 4"):
        export_bundle(tmp_path / "b", *small_models(cfg), cfg, trained=False)
    assert not (tmp_path / "b").exists()


def test_a_flip_test_camera_exports_its_mirror_pass_inside_the_graph(tmp_path):
    cfg = PipelineConfig.with_image_size(32)
    cfg.num_points = 64
    cam, fusion, lidar = small_models(cfg)
    with torch.no_grad():  # an untrained head answers a constant; give the net something to say
        for p in cam.parameters():
            p.add_(0.1 * torch.randn_like(p))
    plain = export_bundle(tmp_path / "plain", cam, fusion, lidar, cfg, trained=False)
    flip = export_bundle(tmp_path / "flip", FlipTest(cam), fusion, lidar, cfg, trained=False)
    assert "flip_test" not in plain["models"]["camera"] and flip["models"]["camera"]["flip_test"] is True
    assert flip["models"]["camera"]["inputs"] == plain["models"]["camera"]["inputs"]
    assert flip["training"]["config"]["onnx_parity_max_abs_diff"]["camera"] <= 1e-4

    def run(bundle, x):
        sess = ort.InferenceSession(
            str(tmp_path / bundle / "camera.onnx"), providers=["CPUExecutionProvider"]
        )
        return sess.run(None, {"image": x})[0]

    x = np.random.default_rng(0).standard_normal((5, 3, 32, 32)).astype(np.float32)
    a, m = run("plain", x), run("plain", x[..., ::-1].copy())
    back = m[:, FLIP, :, ::-1]
    want = a.copy()
    want[..., 1:] = 0.5 * (a[..., 1:] + back[..., :-1])
    np.testing.assert_allclose(run("flip", x), want, atol=1e-5)


def checkpoint_args(tmp_path, camera_train_config=None) -> list[str]:
    """Small camera, fusion and LiDAR-only checkpoints written to tmp_path, as export's arguments."""
    cfg = PipelineConfig.with_image_size(32)
    cfg.num_points = 64
    cam, fusion, lidar = small_models(cfg)
    camera = {"config": cam.cfg.__dict__, "state_dict": cam.state_dict(), "pipeline": cfg.to_dict()}
    if camera_train_config is not None:
        camera["train_config"] = camera_train_config
    args = []
    for name, ckpt in (
        ("camera", camera),
        ("fusion", {"config": fusion.cfg.__dict__, "state_dict": fusion.state_dict()}),
        ("lidar", {"config": lidar.cfg.__dict__, "state_dict": lidar.state_dict()}),
    ):
        torch.save(ckpt, tmp_path / f"{name}.pt")
        args += [f"--{name}", str(tmp_path / f"{name}.pt")]
    return args


@pytest.mark.parametrize(
    ("train_config", "flag", "want"),
    [
        (None, [], False),  # a checkpoint from before the trainer recorded its config
        (None, ["--flip-test"], True),
        ({"flip_test": True}, [], True),
        ({"flip_test": False}, [], False),
        ({"flip_test": True}, ["--no-flip-test"], False),
        (None, ["--no-flip-test"], False),
    ],
)
def test_the_cli_exports_the_flip_test_from_the_flag_or_the_checkpoint(tmp_path, train_config, flag, want):
    from posefuse_train.export import main

    main([*checkpoint_args(tmp_path, train_config), *flag, "--out", str(tmp_path / "b")])
    manifest = json.loads((tmp_path / "b" / "manifest.json").read_text())
    assert manifest["models"]["camera"].get("flip_test", False) is want


def test_the_flip_test_cannot_be_asked_for_and_refused_at_once(tmp_path):
    from posefuse_train.export import main

    both = ["--flip-test", "--no-flip-test"]
    with pytest.raises(SystemExit):
        main([*checkpoint_args(tmp_path, None), *both, "--out", str(tmp_path / "b")])
    assert not (tmp_path / "b").exists()


@pytest.mark.parametrize("blend", [False, True])
def test_the_cli_blends_the_point_networks_when_asked(tmp_path, blend):
    from posefuse_train.export import main

    main([*checkpoint_args(tmp_path), *(["--blend"] if blend else []), "--out", str(tmp_path / "b")])
    manifest = json.loads((tmp_path / "b" / "manifest.json").read_text())
    assert manifest["models"]["point_fusion"].get("blend") == (["fusion", "lidar"] if blend else None)
    assert "blend" not in manifest["models"]["point_lidar"]


def test_a_blend_exports_the_mean_of_its_networks_each_on_the_features_it_takes(tmp_path):
    cfg = PipelineConfig.with_image_size(32)
    cfg.num_points = 64
    cam, fusion, lidar = small_models(cfg)
    for net in (fusion, lidar):
        net.eval()
    blend = Blend([fusion, lidar], ["fusion", "lidar"])
    manifest = export_bundle(tmp_path / "b", cam, blend, lidar, cfg, trained=False)
    assert manifest["models"]["point_fusion"]["blend"] == ["fusion", "lidar"]
    assert "blend" not in manifest["models"]["point_lidar"]
    sess = ort.InferenceSession(str(tmp_path / "b" / "point_fusion.onnx"), providers=["CPUExecutionProvider"])
    x = np.random.default_rng(0).standard_normal((3, 64, 3 + K)).astype(np.float32)
    keypoints, seg = sess.run(None, {"points": x})
    with torch.no_grad():
        t = torch.from_numpy(x)
        (kf, sf), (kl, sl) = fusion(t), lidar(t[..., :3])
    # the two networks answer differently, so the mean is neither of them
    assert (kf - kl).abs().max() > 1e-3
    np.testing.assert_allclose(keypoints, (0.5 * (kf + kl)).numpy(), atol=1e-5)
    np.testing.assert_allclose(seg, torch.sigmoid(0.5 * (sf + sl)).numpy(), atol=1e-5)


def test_a_blend_takes_two_or_more_named_networks():
    cfg = PipelineConfig.with_image_size(32)
    _, fusion, lidar = small_models(cfg)
    with pytest.raises(ValueError):
        Blend([fusion], ["fusion"])
    with pytest.raises(ValueError):
        Blend([fusion, lidar], ["fusion"])
    assert Blend([lidar, fusion], ["lidar", "fusion"]).cfg.in_features == 3 + K
