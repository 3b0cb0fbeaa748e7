"""experiments.blends: errors split along and across the camera's line of sight, pair means, and the
whole command on two bundles that share a camera net."""

import json
import math

import numpy as np
import pytest
import torch
from test_export import small_models

from experiments import blends
from posefuse_train.data import read_meta
from posefuse_train.export import export_bundle
from posefuse_train.keypoints import NAMES, K
from posefuse_train.point_net import Blend


def test_the_line_of_sight_is_turned_into_the_box_frame():
    # camera at (1, 2, 0) in the vehicle frame, box 10 m ahead of it on x, box frame turned 90°
    ext = np.eye(4)
    ext[:3, 3] = [1.0, 2.0, 0.0]
    box = np.array([[11.0, 2.0, 0.0, 0.5, 0.5, 1.8, 0.0]])
    ray = blends.line_of_sight(ext[None], box, np.array([math.pi / 2]))
    # vehicle +x seen from a frame whose x axis points along vehicle +y is that frame's -y
    np.testing.assert_allclose(ray, [[0.0, -1.0, 0.0]], atol=1e-12)
    tilted = blends.line_of_sight(ext[None], np.array([[4.0, 6.0, 0.0, 1, 1, 1, 0]]), np.array([0.0]))
    np.testing.assert_allclose(tilted, [[0.6, 0.8, 0.0]], atol=1e-12)


def test_an_error_splits_into_its_part_along_the_ray_and_the_rest():
    truth = np.zeros((2, K, 3))
    pred = np.zeros((2, K, 3))
    pred[0, 0] = [3.0, 4.0, 0.0]  # 3 along x, 4 across
    pred[1, 0] = [0.0, -2.0, 0.0]  # along -y: 2 along, none across
    ray = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    along, across = blends.split_error(pred, truth, ray)
    assert along[0, 0] == pytest.approx(3.0) and across[0, 0] == pytest.approx(4.0)
    assert along[1, 0] == pytest.approx(2.0) and across[1, 0] == pytest.approx(0.0)
    assert (along[:, 1:] == 0).all() and (across[:, 1:] == 0).all()


def test_the_axes_table_averages_labelled_keypoints_of_each_group():
    wrists = [i for i, n in enumerate(NAMES) if "wrist" in n]
    truth = np.zeros((1, K, 3))
    pred = np.zeros((1, K, 3))
    pred[0, wrists[0]] = [0.0, 0.3, 0.0]  # across only
    pred[0, wrists[1]] = [0.5, 0.0, 0.0]  # along only, but not labelled
    mask = np.ones((1, K), bool)
    mask[0, wrists[1]] = False
    t = blends.axes_table(pred, truth, np.array([[1.0, 0.0, 0.0]]), mask)
    assert t["wrist"] == pytest.approx({"error": 0.3, "along": 0.0, "across": 0.3})
    assert t["all"]["across"] == pytest.approx(0.3 / (K - 1)) and t["hip"]["error"] == 0.0


def test_pair_means_name_every_pair_once():
    nets = {"F0": np.full((1, K, 3), 1.0), "L0": np.full((1, K, 3), 3.0), "L1": np.full((1, K, 3), 5.0)}
    rows = blends.pair_means(nets)
    assert set(rows) == {"F0", "L0", "L1", "mean(F0,L0)", "mean(F0,L1)", "mean(L0,L1)"}
    assert rows["mean(F0,L1)"][0, 0, 0] == 3.0 and rows["mean(L0,L1)"][0, 0, 0] == 4.0


def test_the_command_scores_two_bundles_and_their_pairs(synthetic_sets, tmp_path, capsys):
    _, cfg = read_meta(synthetic_sets[0])
    bundles = []
    for seed in (0, 1):
        cam, fusion, lidar = small_models(cfg)  # one camera net (seeded inside), other point nets
        torch.manual_seed(10 + seed)
        with torch.no_grad():
            for net in (fusion, lidar):
                for p in net.parameters():
                    p.add_(0.1 * torch.randn_like(p))
        bundles.append(tmp_path / f"b{seed}")
        export_bundle(bundles[-1], cam, fusion, lidar, cfg, trained=False)
    out = tmp_path / "blends.json"
    args = ["--test", str(synthetic_sets[1]), "--out", str(out)]
    blends.main([*args, "--bundle", str(bundles[0]), "--bundle", str(bundles[1])])
    report = json.loads(out.read_text())
    assert set(report["axes"]) == {"F0", "L0", "camera"}
    assert {"F0", "L0", "F1", "L1", "mean(F0,L0)", "mean(L0,L1)"} <= set(report["scores"])
    assert report["scores"]["F0"] != report["scores"]["F1"]
    assert "| mean(F0,L0) |" in capsys.readouterr().out
    for part in report["axes"]["F0"].values():
        # the parts of an error are legs of a right triangle: neither exceeds the whole on average
        assert part["along"] <= part["error"] + 1e-12 and part["across"] <= part["error"] + 1e-12


def test_a_bundle_already_blended_is_refused(synthetic_sets, tmp_path):
    _, cfg = read_meta(synthetic_sets[0])
    cam, fusion, lidar = small_models(cfg)
    export_bundle(tmp_path / "b", cam, Blend([fusion, lidar], ["fusion", "lidar"]), lidar, cfg, trained=False)
    with pytest.raises(SystemExit, match="already a blend"):
        blends.main(["--test", str(synthetic_sets[1]), "--bundle", str(tmp_path / "b")])


def test_bundles_with_different_camera_nets_are_refused(synthetic_sets, tmp_path):
    _, cfg = read_meta(synthetic_sets[0])
    bundles = []
    for seed in (0, 1):
        cam, fusion, lidar = small_models(cfg)
        torch.manual_seed(seed)
        with torch.no_grad():
            for p in cam.parameters():
                p.add_(0.1 * seed * torch.randn_like(p))
        bundles.append(tmp_path / f"b{seed}")
        export_bundle(bundles[-1], cam, fusion, lidar, cfg, trained=False)
    args = ["--test", str(synthetic_sets[1]), "--bundle", str(bundles[0]), "--bundle", str(bundles[1])]
    with pytest.raises(SystemExit, match="different camera nets"):
        blends.main(args)
