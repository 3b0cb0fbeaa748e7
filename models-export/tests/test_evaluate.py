import numpy as np
import pytest

from posefuse_train.data import load
from posefuse_train.evaluate import camera_only, evaluate, left_right_swap_rate, with_fallback, with_points
from posefuse_train.keypoints import FLIP, K


def test_camera_only_decodes_and_lifts_over_the_serve_points(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[1])
    s, h = cfg.image_size, cfg.heatmap_size
    # one person; heatmap peak for every keypoint at the cell of serve point 5 -> lifted to (about)
    # the serve points projecting near that cell (eq. 1 with the dataset's temperature)
    one = {k: v[:1] for k, v in d.items()}
    uv = one["serve_uv"][0, 5]
    j, i = int(np.floor(uv[0] * h / s + 0.5)), int(np.floor(uv[1] * h / s + 0.5))
    hm = np.zeros((1, K, h, h), np.float32)
    hm[0, :, i, j] = 1.0
    pred = camera_only(hm, one, cfg)
    cell_px = np.array([j * s / h, i * s / h])
    d2 = (((one["serve_uv"][0] - cell_px) / s) ** 2).sum(axis=1)
    w = np.exp(-cfg.lift_temperature * (d2 - d2.min()))
    want = (w[:, None] * one["serve_xyz"][0]).sum(axis=0) / w.sum()
    np.testing.assert_allclose(pred[0, 0], want, atol=1e-5)
    assert np.allclose(pred[0], pred[0, :1])


def test_fallback_uses_camera_answers_below_min_points_only(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[1])
    d = {k: v[:3].copy() for k, v in d.items()}
    d["points_count"][:] = [cfg.min_points, cfg.min_points - 1, cfg.min_points + 1]
    pred = np.zeros((3, K, 3), np.float32)
    cam = np.ones((3, K, 3), np.float32)
    out = with_fallback(pred, cam, d, cfg)
    # exactly at min_points the point network answers (the server's `>=`); one below, the camera
    assert (out[0] == 0).all() and (out[1] == 1).all() and (out[2] == 0).all()


def test_left_right_swap_rate_counts_persons_read_the_wrong_way_round():
    rng = np.random.default_rng(0)
    gt = rng.normal(0.0, 0.3, (4, K, 3))
    vis = np.ones((4, K), bool)
    pred = gt + 0.01
    pred[1] = gt[1][FLIP]  # facing read backwards: left and right exchanged
    pred[2] = gt[2][FLIP] + 0.02
    vis[3, 1:] = False  # only the nose: too few keypoints to tell, skipped
    assert left_right_swap_rate(pred, gt, vis) == 2 / 3
    assert left_right_swap_rate(gt, gt, vis) == 0.0
    assert left_right_swap_rate(pred, gt, np.zeros((4, K), bool)) is None


def test_occluded_keypoints_count_in_the_headline_and_apart_in_the_breakdown(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[1])
    vis3, occ3 = d["kp3d_visible"] > 0, d["kp3d_occluded"] > 0
    assert occ3.any() and not (vis3 & occ3).any()
    # visible keypoints 5 cm off along x, occluded ones 30 cm off
    off = np.where(occ3, 0.3, 0.05)
    pred = d["kp3d"].copy()
    pred[..., 0] += off
    r = evaluate(pred, d, cfg)
    labelled = vis3 | occ3
    assert r["mpjpe_3d_m"] == pytest.approx(off[labelled].mean(), rel=1e-5)
    assert r["breakdown"]["visible"]["mpjpe_3d_m"] == pytest.approx(0.05, rel=1e-5)
    assert r["breakdown"]["occluded"]["mpjpe_3d_m"] == pytest.approx(0.3, rel=1e-5)
    assert r["pck_3d_20cm"] == pytest.approx(vis3.sum() / labelled.sum(), rel=1e-9)


def test_with_points_scores_only_the_persons_the_point_networks_answer(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[1])
    d = {k: v[:4].copy() for k, v in d.items()}
    d["points_count"][:] = [cfg.min_points, cfg.min_points - 1, cfg.min_points + 5, 0]
    # the point networks' persons 5 cm off, the camera-lifted ones 1 m off
    few = d["points_count"] < cfg.min_points
    pred = d["kp3d"].copy()
    pred[..., 0] += np.where(few, 1.0, 0.05)[:, None]
    labelled = (d["kp3d_visible"] > 0) | (d["kp3d_occluded"] > 0)
    assert labelled[~few].any() and labelled[few].any()
    assert evaluate(pred, d, cfg)["mpjpe_3d_m"] > 0.1
    r = with_points(pred, d, cfg)
    assert r["mpjpe_3d_m"] == pytest.approx(0.05, rel=1e-5)
    assert r["count_3d"] == int(labelled[~few].any(axis=1).sum())
