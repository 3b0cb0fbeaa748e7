"""tools/evaluate_bundle: the server's mode policy, person by person, on fixtures."""

import json

import numpy as np
import torch
from synthetic import write_dataset

from posefuse_train.config import CameraNetConfig, PipelineConfig, PointNetConfig
from posefuse_train.export import export_bundle, untrained_models
from posefuse_train.keypoints import K
from posefuse_train.point_net import PointNet
from tools.evaluate_bundle import evaluate_bundle

BOX = ("center_x", "center_y", "center_z", "length", "width", "height", "heading")


def test_modes_follow_the_image_and_min_points_and_forced_modes_refuse_frames_without_an_image(tmp_path):
    root = write_dataset(tmp_path / "data", 12, seed=5, image_size=32, num_points=64, cap=96)
    shard = root / "shards" / "shard-00000.npz"
    z = dict(np.load(shard))
    z["frame_index"] = np.array([0] * 6 + [3] * 6, np.int32)  # two fixtures; frame 3 has no image
    np.savez(shard, **z)
    for f, (a, b) in ((0, (0, 6)), (3, (6, 12))):
        persons = [
            {
                "id": f"p{i}",
                "box_2d": {"center_x": 1.0},
                "box_3d": dict(zip(BOX, map(float, z["box3d"][i]), strict=True)),
            }
            for i in range(a, b)
        ]
        frame = {"persons": persons, **({"image": "jpeg"} if f == 0 else {})}
        (root / "requests").mkdir(exist_ok=True)
        (root / "requests" / f"frame-{f:06d}.json").write_text(json.dumps(frame))
    counts = z["points_count"]
    cfg = PipelineConfig.with_image_size(32)
    cfg.num_points = 64
    cfg.min_points = int(np.sort(counts[:6])[3])  # persons of frame 0 on both sides, one exactly at it
    torch.manual_seed(0)
    cam, _, _ = untrained_models(cfg, CameraNetConfig(backbone="resnet18-w16", deconv_channels=16))
    small = dict(local_channels=(16,), global_channels=(32,), head_channels=(32,), seg_channels=(16,))
    fusion, lidar = PointNet(PointNetConfig(3 + K, **small)), PointNet(PointNetConfig(3, **small))
    export_bundle(tmp_path / "b", cam, fusion, lidar, cfg, trained=False)

    reports, pred = evaluate_bundle(tmp_path / "b", root, True, ("auto", "fusion", "lidar", "camera"))
    for mode in ("fusion", "camera"):
        assert pred[mode]["frame-000003.json"] == {"refused": True, "persons": {}, "skipped": []}
        assert reports[mode]["failed_frames"] == 1 and reports[mode]["persons"] == 6
    assert reports["lidar"]["failed_frames"] == 0 and reports["lidar"]["persons"] == 12
    auto = pred["auto"]
    for i in range(12):
        frame, pid = ("frame-000000.json", "frame-000003.json")[i >= 6], f"p{i}"
        got = auto[frame]["persons"][pid]
        want = "lidar" if i >= 6 else "fusion" if counts[i] >= cfg.min_points else "camera"
        assert got["mode"] == want and got["num_points"] == counts[i]
        assert got["xyz"] == pred[want][frame]["persons"][pid]["xyz"]
    modes = [p["mode"] for p in auto["frame-000000.json"]["persons"].values()]
    assert modes.count("fusion") == 3 and modes.count("camera") == 3
    # the networks differ, so the modes are told apart by their keypoints too
    a, b = (np.array(pred[m]["frame-000000.json"]["persons"]["p0"]["xyz"]) for m in ("fusion", "lidar"))
    assert np.abs(a - b).max() > 1e-3
