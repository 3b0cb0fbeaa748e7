import math

import numpy as np
import torch

from posefuse_train import labels, metrics
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


def test_occluded_labels_lie_on_the_2d_labels_ray_at_the_box_centres_depth(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[0])
    lab = labels.on_rays_at_box_depth(d)
    vehicle = metrics.local_to_vehicle(lab, d["box3d"], d["frame_yaw"])
    # they project back onto the 2D labels ...
    crop = d["crop"].astype(np.float64)
    px = metrics.project(vehicle, d["intrinsic"], d["extrinsic"])
    np.testing.assert_allclose((px - crop[:, None, :2]) * crop[:, None, 2:3], d["kp2d"], atol=1e-3)
    # ... at the depth of the box centre (the synthetic camera looks along +x from the origin)
    np.testing.assert_allclose(vehicle[..., 0], np.repeat(d["box3d"][:, :1], 13, axis=1), atol=1e-4)


def test_pseudo_labels_give_occluded_keypoints_without_a_point_near_them_a_ray_label(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[0])
    base = labels.pseudo_labels(d, cfg, t_r=200.0, depth_correction=True)
    assert not (base["weight"][d["kp2d_occluded"] > 0] > 0).any()
    # an occluded keypoint gets a label exactly when no point lies within the radius (5 % of S)
    with_occ = labels.pseudo_labels(d, cfg, t_r=200.0, depth_correction=True, occluded_weight=0.5)
    nearest = labels.nearest_d2(d["kp2d"], d["points_uv"], d["points_count"], cfg.image_size)
    added = (with_occ["weight"] > 0) & (base["weight"] == 0)
    np.testing.assert_array_equal(added, (d["kp2d_occluded"] > 0) & (nearest > 0.05**2))
    assert 0 < added.sum() < (d["kp2d_occluded"] > 0).sum()
    np.testing.assert_array_equal(with_occ["weight"][~added], base["weight"][~added])
    np.testing.assert_array_equal(with_occ["kp3d"][~added], base["kp3d"][~added])
    # with no point counted, every occluded 2D label is one that no point is near
    empty = dict(d, points_count=np.zeros_like(d["points_count"]))
    lab = labels.pseudo_labels(empty, cfg, t_r=200.0, depth_correction=True, occluded_weight=0.5)
    occ = d["kp2d_occluded"] > 0
    assert occ.sum() > 20
    np.testing.assert_array_equal(lab["weight"] > 0, occ)
    np.testing.assert_allclose(lab["weight"][occ], 0.5)
    np.testing.assert_allclose(lab["kp3d"][occ], labels.on_rays_at_box_depth(d)[occ], atol=1e-6)
    assert not lab["visible"].any()  # segmentation never treats an occluder's points as the joint
    # a smaller radius labels more of them; the visible ones' labels never change
    small = labels.pseudo_labels(
        d, cfg, t_r=200.0, depth_correction=True, occluded_weight=0.5, occluded_radius=1e-4
    )
    assert ((small["weight"] > 0) & occ).sum() > added.sum()
    np.testing.assert_array_equal(small["visible"], base["visible"])


def test_snapped_labels_keep_their_depth_and_land_on_the_2d_labels_rays(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[0])
    base = labels.pseudo_labels(d, cfg, t_r=200.0, depth_correction=True)
    snap = labels.pseudo_labels(d, cfg, t_r=200.0, depth_correction=True, snap_to_rays=True)
    ok = base["visible"]
    np.testing.assert_array_equal(snap["visible"], ok)
    np.testing.assert_array_equal(snap["weight"], base["weight"])
    assert not snap["kp3d"][~ok].any()
    vb = metrics.local_to_vehicle(base["kp3d"], d["box3d"], d["frame_yaw"])
    vs = metrics.local_to_vehicle(snap["kp3d"], d["box3d"], d["frame_yaw"])
    # the synthetic camera looks along +x from the origin: depth is x
    np.testing.assert_allclose(vs[..., 0][ok], vb[..., 0][ok], atol=1e-4)
    crop = d["crop"].astype(np.float64)
    px = (metrics.project(vs, d["intrinsic"], d["extrinsic"]) - crop[:, None, :2]) * crop[:, None, 2:3]
    np.testing.assert_allclose(px[ok], d["kp2d"][ok], atol=1e-3)
    moved = np.linalg.norm(snap["kp3d"] - base["kp3d"], axis=2)[ok]
    assert moved.mean() > 0.005  # eq. 1's labels were beside the rays


def test_relabelled_puts_every_2d_label_on_its_ray_at_the_depth_the_first_round_and_the_nets_give(
    synthetic_sets,
):
    d, cfg, _ = load(synthetic_sets[0])
    # a keypoint without a label has a finite 2D position in converted Waymo data ([0, 0])
    unlabelled = np.zeros_like(d["kp2d_visible"], bool)
    unlabelled[::3, 5] = True
    d = dict(d, kp2d=np.where(unlabelled[..., None], 0.0, d["kp2d"]))
    d.update({k: np.where(unlabelled, 0, d[k]) for k in ("kp2d_visible", "kp2d_occluded")})
    lab = labels.pseudo_labels(d, cfg, t_r=200.0, depth_correction=True, occluded_weight=0.5)
    # a first round's prediction: the labels where there are some, the box centre elsewhere,
    # moved 0.3 m deeper (the synthetic camera looks along +x from the origin: depth is x)
    vehicle_lab = metrics.local_to_vehicle(lab["kp3d"], d["box3d"], d["frame_yaw"])
    start = np.where((lab["weight"] > 0)[..., None], vehicle_lab, d["box3d"][:, None, :3])
    pred = metrics.vehicle_to_local(start + [0.3, 0.0, 0.0], d["box3d"], d["frame_yaw"])
    two = labels.relabelled(lab, d, pred, 0.25)
    np.testing.assert_array_equal(two["visible"], lab["visible"])
    ok = lab["visible"]
    labelled = (d["kp2d_visible"] > 0) | (d["kp2d_occluded"] > 0)
    assert ok.sum() > 20 and (labelled & ~ok).sum() > 20
    # first-round labels keep their weights, every other labelled 2D keypoint gets the given one
    np.testing.assert_array_equal(two["weight"][ok], lab["weight"][ok])
    np.testing.assert_allclose(two["weight"][labelled & ~ok], 0.25)
    assert not two["weight"][~labelled].any() and not two["kp3d"][~labelled].any()
    assert np.isfinite(d["kp2d"][unlabelled]).all() and unlabelled.sum() > 5
    # depths: the mean of the label's and the prediction's where there was a label, else the prediction's
    vs = metrics.local_to_vehicle(two["kp3d"], d["box3d"], d["frame_yaw"])
    np.testing.assert_allclose(vs[..., 0][ok], vehicle_lab[..., 0][ok] + 0.15, atol=1e-4)
    other = labelled & ~ok
    np.testing.assert_allclose(
        vs[..., 0][other], (d["box3d"][:, None, 0] + 0.3).repeat(13, 1)[other], atol=1e-4
    )
    # ... and each on its 2D label's ray
    crop = d["crop"].astype(np.float64)
    px = (metrics.project(vs, d["intrinsic"], d["extrinsic"]) - crop[:, None, :2]) * crop[:, None, 2:3]
    np.testing.assert_allclose(px[labelled], d["kp2d"][labelled], atol=1e-3)
