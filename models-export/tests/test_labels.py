import math

import numpy as np
import torch

from posefuse_train import labels
from posefuse_train.data import load
from posefuse_train.train import rotate_z


def test_lift_matches_a_hand_computed_softmax():
    # S = 10, T = 100: point A at distance 1 px (d = 0.1, logit -1), point B at 2 px (logit -4),
    # a third point has no projection and must be ignored.
    kp = np.array([[[5.0, 5.0]]], np.float32)
    uv = np.array([[[6.0, 5.0], [5.0, 7.0], [np.nan, np.nan]]], np.float32)
    xyz = np.array([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [100.0, 100.0, 100.0]]], np.float32)
    out = labels.lift(kp, uv, xyz, None, 10, 100.0)
    wa, wb = math.exp(-1), math.exp(-4)
    np.testing.assert_allclose(out[0, 0], [wa / (wa + wb), wb / (wa + wb), 0.0], atol=1e-6)
    r = labels.reliability(kp, uv, None, 10, 2.0)
    np.testing.assert_allclose(r[0, 0], math.exp(-0.02), rtol=1e-6)
    assert np.isnan(labels.lift(kp, uv[:, 2:], xyz[:, 2:], None, 10, 100.0)).all()
    assert labels.reliability(kp, uv[:, 2:], None, 10, 2.0)[0, 0] == 0.0


def test_rows_past_the_count_are_ignored_and_high_temperature_picks_the_nearest():
    kp = np.array([[[0.0, 0.0]]], np.float32)
    uv = np.array([[[1.0, 0.0], [3.0, 0.0], [0.0, 0.0]]], np.float32)  # row 2 is padding
    xyz = np.array([[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [9.0, 9.0, 9.0]]], np.float32)
    out = labels.lift(kp, uv, xyz, np.array([2]), 64, 1e7)
    np.testing.assert_allclose(out[0, 0], [1.0, 2.0, 3.0])
    r = labels.reliability(kp, uv, np.array([2]), 64, 64.0**2)  # T_r * d^2 = 1 for d = 1 px
    np.testing.assert_allclose(r[0, 0], math.exp(-1.0), rtol=1e-6)


def test_segmentation_labels_use_the_radius_and_visibility():
    kp = np.array([[[10.0, 10.0], [30.0, 30.0]]], np.float32)
    vis = np.array([[1, 0]])
    uv = np.array([[[10.0, 12.9], [10.0, 13.1], [30.0, 30.0], [np.nan, np.nan]]], np.float32)
    lab = labels.segmentation_labels(kp, vis, uv, 64, 3.0 / 64)  # r = 3 px
    np.testing.assert_array_equal(lab[0], [[1, 0], [0, 0], [0, 0], [0, 0]])
    lab_t = labels.segmentation_labels(
        torch.from_numpy(kp), torch.from_numpy(vis), torch.from_numpy(uv), 64, 3 / 64
    )
    np.testing.assert_array_equal(lab_t.numpy(), lab)


def test_push_along_rays_moves_away_from_the_sensor():
    lab = np.array([[[3.0, 4.0, 0.0]]], np.float32)
    out = labels.push_along_rays(lab, np.zeros((1, 3), np.float32), np.array([[0.5]], np.float32))
    np.testing.assert_allclose(out[0, 0], [3.3, 4.4, 0.0], rtol=1e-6)
    off = labels.depth_offsets(np.array([1.75, 3.5], np.float32))
    np.testing.assert_allclose(off[1], 2 * labels.JOINT_DEPTH_M)


def test_pseudo_labels_on_shards(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[0])
    lab = labels.pseudo_labels(d, cfg, t_r=200.0)
    assert lab["kp3d"].shape == (96, 13, 3)
    # only visible 2D keypoints produce labels; labels are near the truth (surface bias ~5 cm)
    assert not (lab["visible"] & (d["kp2d_visible"] == 0)).any()
    err = np.linalg.norm(lab["kp3d"] - d["kp3d"], axis=2)[lab["visible"]]
    assert 0.02 < err.mean() < 0.15
    fixed = labels.pseudo_labels(d, cfg, t_r=200.0, depth_correction=True)
    err2 = np.linalg.norm(fixed["kp3d"] - d["kp3d"], axis=2)[lab["visible"]]
    assert err2.mean() < err.mean()
    # rotating points and labels together commutes with label generation (uv are unchanged)
    ang = torch.tensor([0.7])
    pts = torch.from_numpy(d["points_xyz"][:1])
    rot = labels.lift(
        d["kp2d"][:1],
        d["points_uv"][:1],
        rotate_z(pts, ang).numpy(),
        d["points_count"][:1],
        cfg.image_size,
        cfg.lift_temperature,
    )
    want = rotate_z(
        torch.from_numpy(
            labels.lift(
                d["kp2d"][:1],
                d["points_uv"][:1],
                d["points_xyz"][:1],
                d["points_count"][:1],
                cfg.image_size,
                cfg.lift_temperature,
            )
        ),
        ang,
    )
    np.testing.assert_allclose(rot, want.numpy(), atol=1e-5)
