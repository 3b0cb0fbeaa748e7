import dataclasses

import numpy as np

from experiments.heading_error import person_errors, with_heading_error
from posefuse_train import metrics
from posefuse_train.data import load
from posefuse_train.evaluate import evaluate


def test_a_heading_error_turns_the_model_frame_but_not_the_world(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[1])
    shifted = with_heading_error(d, np.radians(30.0), cfg)
    # the same points and truth in the vehicle frame, seen through the wrong heading
    for key in ("points_xyz", "serve_xyz", "kp3d", "sensor_xyz"):
        local, turned = d[key].reshape(len(d[key]), -1, 3), shifted[key].reshape(len(d[key]), -1, 3)
        want = metrics.local_to_vehicle(local, d["box3d"], d["frame_yaw"])
        got = metrics.local_to_vehicle(turned, shifted["box3d"], shifted["frame_yaw"])
        np.testing.assert_allclose(got, want, atol=1e-4)
    # ...but not the same model inputs: a heading-aligned network sees a turned body
    assert np.abs(shifted["serve_xyz"] - d["serve_xyz"]).max() > 0.05
    np.testing.assert_array_equal(shifted["serve_uv"], d["serve_uv"])
    r = evaluate(shifted["kp3d"], shifted, cfg)
    assert r["oks_acc_3d"] == 1.0 and r["oks_acc_2d"] == 1.0
    # the original truth in the turned frame is off by the turn
    assert evaluate(d["kp3d"], shifted, cfg)["mpjpe_3d_m"] > 0.01


def test_the_view_frame_does_not_follow_a_wrong_heading(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[1])
    view = dataclasses.replace(cfg, rotate_by_heading=False, frame="view")
    shifted = with_heading_error(d, person_errors(len(d["box3d"]), "uniform", 3), view)
    for key in ("points_xyz", "serve_xyz", "kp3d", "sensor_xyz", "frame_yaw"):
        np.testing.assert_array_equal(shifted[key], d[key])
    assert np.abs(shifted["box3d"][:, 6] - d["box3d"][:, 6]).max() > 0.5


def test_person_errors_draw_a_sign_per_person_or_a_uniform_angle():
    e = person_errors(400, "45", seed=1)
    np.testing.assert_allclose(np.abs(e), np.radians(45.0))
    assert 100 < (e > 0).sum() < 300
    u = person_errors(400, "uniform", seed=1)
    assert np.abs(u).max() <= np.pi and np.abs(u).max() > 2.5 and np.abs(u).min() < 0.5
    np.testing.assert_array_equal(person_errors(400, "uniform", seed=1), u)
