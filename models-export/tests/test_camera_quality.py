"""experiments.camera_quality: heatmaps drawn from the 2D labels with a chosen error, and the whole
command on a tiny set."""

import dataclasses
import json

import numpy as np

from experiments import camera_quality
from posefuse_train import data as data_mod
from posefuse_train import evaluate
from posefuse_train.keypoints import FLIP, NAMES
from posefuse_train.metrics import labelled


def peaks(raw: np.ndarray, image_size: int) -> np.ndarray:
    """Each channel's peak cell centre in model pixels [M,K,2] (x, y)."""
    m, k, h, w = raw.shape
    flat = raw.reshape(m, k, -1).argmax(axis=2)
    cell = image_size / h
    return np.stack([(flat % w) * cell, (flat // w) * cell], axis=2)


def test_without_error_each_labelled_keypoint_peaks_at_its_label_and_the_rest_are_empty(synthetic_sets):
    _, test = synthetic_sets
    d, cfg, _ = data_mod.load(test)
    raw = camera_quality.synthetic_heatmaps(d, cfg.image_size, 8, sigma=0.0, swap=0.0, seed=0)
    known = labelled(d, 2)
    cell = cfg.image_size / 8
    inside = known & (d["kp2d"] > -cell / 2).all(axis=2) & (d["kp2d"] < cfg.image_size - cell / 2).all(axis=2)
    assert inside.sum() > 100
    np.testing.assert_allclose(peaks(raw, cfg.image_size)[inside], d["kp2d"][inside], atol=cell / 2 + 1e-4)
    assert raw[inside].max(axis=(1, 2)).min() > 0.5
    assert (raw[~known] == 0).all()


def test_a_swapped_person_has_left_and_right_exchanged(synthetic_sets):
    _, test = synthetic_sets
    d, cfg, _ = data_mod.load(test)
    plain = camera_quality.synthetic_heatmaps(d, cfg.image_size, 8, sigma=0.0, swap=0.0, seed=0)
    swapped = camera_quality.synthetic_heatmaps(d, cfg.image_size, 8, sigma=0.0, swap=1.0, seed=0)
    np.testing.assert_array_equal(swapped, plain[:, FLIP])
    assert NAMES[FLIP[NAMES.index("left_wrist")]] == "right_wrist"


def test_the_camera_only_score_falls_as_the_error_grows(synthetic_sets):
    _, test = synthetic_sets
    d, cfg, _ = data_mod.load(test)
    cfg = dataclasses.replace(cfg, heatmap_size=8)

    def score(sigma: float) -> float:
        raw = camera_quality.synthetic_heatmaps(d, cfg.image_size, 8, sigma=sigma, swap=0.0, seed=3)
        return evaluate.evaluate(evaluate.camera_only(raw, d, cfg), d, cfg)["oks_acc_2d"]

    exact, rough = score(0.0), score(0.15)
    assert exact - rough > 0.3, (exact, rough)


def test_the_command_trains_one_lidar_net_and_a_fusion_net_per_level(synthetic_sets, tmp_path):
    train, test = synthetic_sets
    out = tmp_path / "run"
    args = ["--train", str(train), "--test", str(test), "--out", str(out), "--levels", "0:0,0.1:0.5"]
    camera_quality.main([*args, "--heatmap-size", "8", "--smoothing-sigma", "1", "--point-steps", "2"])
    r = json.loads((out / "results.json").read_text())
    assert r["supervision"] == "pseudo"
    assert [(lv["sigma"], lv["swap"]) for lv in r["levels"]] == [(0.0, 0.0), (0.1, 0.5)]
    for lv in r["levels"]:
        assert set(lv) >= {"camera_only", "fusion", "lidar", "blend"}
        assert 0.0 <= lv["fusion"]["oks_3d"] <= 1.0 and lv["lidar"]["mpjpe_m"] > 0
    exact, rough = (lv["camera_only"]["oks_2d"] for lv in r["levels"])
    assert exact > rough
    truth = tmp_path / "truth"
    common = ["--heatmap-size", "8", "--smoothing-sigma", "1", "--point-steps", "2", "--levels", "0:0"]
    camera_quality.main(
        ["--train", str(train), "--test", str(test), "--out", str(truth), *common, "--supervision", "truth"]
    )
    r = json.loads((truth / "results.json").read_text())
    assert r["supervision"] == "truth" and len(r["levels"]) == 1
    # with --self-train, each level also trains and scores a second round
    rounds = tmp_path / "rounds"
    camera_quality.main(
        ["--train", str(train), "--test", str(test), "--out", str(rounds), *common, "--self-train", "0.5"]
    )
    r = json.loads((rounds / "results.json").read_text())
    second = r["levels"][0]["round2"]
    assert r["self_train"] == 0.5 and set(second) == {"fusion", "lidar", "blend", "labels"}
    assert second["labels"] > 0 and second["lidar"]["mpjpe_m"] != r["levels"][0]["lidar"]["mpjpe_m"]


def test_truth_labels_are_every_labelled_3d_keypoint_at_weight_one(synthetic_sets):
    _, test = synthetic_sets
    d, _, _ = data_mod.load(test)
    lab = camera_quality.truth_labels(d)
    known = labelled(d, 3)
    np.testing.assert_array_equal(lab["visible"], known)
    np.testing.assert_array_equal(lab["weight"], known.astype(np.float32))
    np.testing.assert_allclose(lab["kp3d"][known], d["kp3d"][known])
    assert (lab["kp3d"][~known] == 0).all() and np.isfinite(lab["kp3d"]).all()
    some = np.zeros_like(known)
    some[:, :3] = True
    part = camera_quality.truth_labels(d, some)
    np.testing.assert_array_equal(part["visible"], known & some)
    assert (part["weight"][:, 3:] == 0).all()
