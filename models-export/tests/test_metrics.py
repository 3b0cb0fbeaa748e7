import json
import math

import numpy as np
import pytest
from conftest import GOLDEN

from posefuse_train import metrics
from posefuse_train.data import load
from posefuse_train.evaluate import evaluate
from posefuse_train.keypoints import OKS_SCALES, K


def test_person_oks_averages_visible_keypoints_and_pools_errors():
    s3 = 0.8
    f = [1.0] * 4 + [2.0] * 2 + [100.0] * 7
    pred = np.array([[[f[k] * OKS_SCALES[k] * s3, 0, 0] for k in range(K)]])
    vis = np.array([[k < 6 for k in range(K)]])
    e = metrics.evaluate_persons(pred, np.zeros((1, K, 3)), vis, np.array([s3]))
    want = (4 * math.exp(-0.5) + 2 * math.exp(-2)) / 6
    assert abs(e["oks"][0] - want) < 1e-12
    assert np.isnan(e["per_keypoint_oks"][0, 6]) and np.isnan(e["errors"][0, 12])
    r = metrics.report(e, None)
    assert r["count_3d"] == 1 and abs(r["mean_oks_3d"] - want) < 1e-12
    assert r["oks_acc_3d"] == pytest.approx(np.mean([want >= t for t in metrics.THRESHOLDS]))


def test_missing_predictions_score_zero_and_cost_the_pem_clip():
    gt = np.zeros((1, K, 3))
    pred = np.zeros((1, K, 3))
    pred[0, 0] = np.nan
    e = metrics.evaluate_persons(pred, gt, np.ones((1, K), bool), np.array([1.0]))
    assert e["per_keypoint_oks"][0, 0] == 0.0 and np.isnan(e["errors"][0, 0])
    r = metrics.report(e, None)
    assert r["pem_3d_m"] == pytest.approx(0.25 / K)
    assert r["pck_3d_10cm"] == pytest.approx((K - 1) / K)
    assert r["mpjpe_3d_m"] == 0.0


def test_oks_acc_counts_thresholds_inclusively():
    assert metrics.oks_acc(np.array([0.55])) == pytest.approx(0.2)
    assert metrics.oks_acc(np.array([1.0, 0.0])) == pytest.approx(0.5)
    assert metrics.oks_acc(np.array([])) is None


def test_ground_truth_scores_perfectly_in_3d_and_after_projection(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[1])
    r = evaluate(d["kp3d"], d, cfg)
    assert r["oks_acc_3d"] == 1.0 and r["mpjpe_3d_m"] < 1e-6
    # local -> vehicle -> image must land on the exact 2D projections
    assert r["oks_acc_2d"] == 1.0 and r["mpjpe_2d_px"] < 1e-3
    shifted = d["kp3d"] + np.array([0.1, 0.0, 0.0], np.float32)
    r2 = evaluate(shifted, d, cfg)
    assert r2["mpjpe_3d_m"] == pytest.approx(0.1, abs=1e-6) and r2["oks_acc_3d"] < 1.0


def test_metrics_match_the_server_golden_cases():
    path = GOLDEN / "metrics.json"
    if not path.exists():
        pytest.fail(f"{path} is missing: it is written from crates/core/src/metrics and pins the Python copy")
    g = json.loads(path.read_text())
    assert g["cases"], "no golden cases"
    for i, c in enumerate(g["cases"]):
        pred = np.array([[np.nan if v is None else v for v in p] for p in c["pred"]], np.float64)[None]
        gt = np.array(c["gt"], np.float64)[None]
        vis = (np.array(c["visibility"]) > 0)[None]  # Waymo's mask: occluded (1) and visible (2)
        e = metrics.evaluate_persons(pred, gt, vis, np.array([c["box_scale"]]))
        if c["oks"] is None:
            assert np.isnan(e["oks"][0]), i
        else:
            assert e["oks"][0] == pytest.approx(c["oks"], rel=1e-9, abs=1e-12), i
        for k, want in enumerate(c["per_keypoint_oks"]):
            got = e["per_keypoint_oks"][0, k]
            assert np.isnan(got) if want is None else got == pytest.approx(want, rel=1e-9, abs=1e-12), (i, k)
        err = e["errors"][0]
        mp = float(np.nanmean(err)) if np.isfinite(err).any() else None
        assert (mp is None) if c["mpjpe"] is None else mp == pytest.approx(c["mpjpe"], rel=1e-9, abs=1e-12), i
    assert metrics.oks_acc(np.array(g["oks_acc"]["oks"])) == pytest.approx(g["oks_acc"]["value"], abs=1e-12)


def test_box_frame_matches_the_server_golden_vectors():
    """tests/golden/points.json: vehicle points and their model-input coordinates (box and view
    frames) as the Rust pipeline computes them; the Python inverse maps the latter back onto the former."""
    path = GOLDEN / "points.json"
    if not path.exists():
        pytest.fail(f"{path} is missing: it is written from crates/core/src/pipeline and pins the Python "
                    "copy")
    g = json.loads(path.read_text())
    b = g["box3d"]
    box = np.array(
        [[b[k] for k in ("center_x", "center_y", "center_z", "length", "width", "height", "heading")]]
    )
    for frame in ("box_heading", "view"):
        local = np.array(g[frame]["local"], np.float64)[None]
        yaw = np.array([g[frame]["frame_yaw"]])
        vehicle = metrics.local_to_vehicle(local, box, yaw)
        np.testing.assert_allclose(vehicle[0], g["vehicle"], rtol=0, atol=1e-9)
        # the frame's yaw matters: without it the points land elsewhere
        assert np.abs(metrics.local_to_vehicle(local, box, np.zeros(1))[0] - g["vehicle"]).max() > 0.1
    assert g["box_heading"]["frame_yaw"] == b["heading"]
    # the view frame looks along the ray from the sensor to the box centre
    o = g["view_origin"]
    assert g["view"]["frame_yaw"] == pytest.approx(np.arctan2(b["center_y"] - o[1], b["center_x"] - o[0]))


def test_projection_is_nan_where_the_lens_polynomial_folds_back():
    # A camera at the origin looking along +x with strong barrel distortion (k2 = -0.33): at 50°
    # off-axis the unchecked pixel folds back inside the 1920x1280 image; the server's camera
    # model (and Waymo's) refuses it, and so must the trainer's.
    intrinsic = np.array([[2055.0, 2055.0, 960.0, 640.0, 0.0, -0.33, 0.0, 0.0, 0.0]])
    extrinsic = np.eye(4).reshape(1, 16)
    bearings = np.radians([0.0, 20.0, 50.0, 60.0, 180.0])
    pts = np.stack([10 * np.cos(bearings), 10 * np.sin(bearings), np.zeros(5)], axis=1)[None]
    uv = metrics.project(pts, intrinsic, extrinsic)[0]
    assert np.isfinite(uv[:2]).all()
    assert np.isnan(uv[2:]).all()
    # the folded pixel would have been inside the image
    un = -np.tan(bearings[2])
    folded = 960 + 2055 * un * (1 - 0.33 * un**4)
    assert 0 <= folded < 1920


def test_unproject_inverts_project_through_a_distorted_lens_and_a_turned_camera():
    # A camera 1.5 m forward and 2 m up, yawed 10° and pitched 3°, with every lens term set.
    yaw, pitch = np.radians(10.0), np.radians(3.0)
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    ry = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]])
    ext = np.eye(4)
    ext[:3, :3], ext[:3, 3] = rz @ ry, [1.5, 0.0, 2.0]
    intrinsic = np.array([[2055.0, 2050.0, 950.0, 630.0, -0.05, 0.02, 0.001, -0.002, 0.01]])
    rng = np.random.default_rng(3)
    pts = np.stack([rng.uniform(10, 40, 20), rng.uniform(-3, 3, 20), rng.uniform(0, 3, 20)], axis=1)[None]
    px = metrics.project(pts, intrinsic, ext.reshape(1, 16))
    assert np.isfinite(px).all()
    cam_depth = np.einsum("j,kj->k", ext[:3, 0], pts[0] - ext[:3, 3])[None]
    back = metrics.unproject(px, cam_depth, intrinsic, ext.reshape(1, 16))
    np.testing.assert_allclose(back, pts, atol=1e-6)
    np.testing.assert_allclose(metrics.camera_depth(pts, ext.reshape(1, 16)), cam_depth)
    np.testing.assert_allclose(metrics.camera_depth(pts[:, 0], ext.reshape(1, 16)), cam_depth[:, 0])
    # half the depth: the same pixel, half-way to the camera
    half = metrics.unproject(px, cam_depth / 2, intrinsic, ext.reshape(1, 16))
    np.testing.assert_allclose(metrics.project(half, intrinsic, ext.reshape(1, 16)), px, atol=1e-6)
    np.testing.assert_allclose(half, (pts + ext[:3, 3]) / 2, atol=1e-6)


def test_vehicle_to_local_inverts_local_to_vehicle():
    rng = np.random.default_rng(4)
    local = rng.normal(0, 1, (3, 5, 3))
    box = np.array([[10.0, -2.0, 0.9, 0.6, 0.7, 1.8, 0.3]] * 3) + rng.normal(0, 1, (3, 7))
    yaw = rng.uniform(-np.pi, np.pi, 3)
    vehicle = metrics.local_to_vehicle(local, box, yaw)
    np.testing.assert_allclose(metrics.vehicle_to_local(vehicle, box, yaw), local, atol=1e-12)
    assert np.abs(metrics.vehicle_to_local(vehicle, box, yaw + 0.1) - local).max() > 0.01
