import numpy as np

from experiments.heading_error import with_heading_error
from posefuse_train import metrics
from posefuse_train.data import load
from posefuse_train.evaluate import evaluate


def test_a_heading_error_turns_the_model_frame_but_not_the_world(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[1])
    shifted = with_heading_error(d, np.radians(30.0))
    # the same points and truth in the vehicle frame, seen through the wrong heading
    for key in ("points_xyz", "serve_xyz", "kp3d", "sensor_xyz"):
        local, turned = d[key].reshape(len(d[key]), -1, 3), shifted[key].reshape(len(d[key]), -1, 3)
        want = metrics.local_to_vehicle(local, d["box3d"], cfg.rotate_by_heading)
        got = metrics.local_to_vehicle(turned, shifted["box3d"], cfg.rotate_by_heading)
        np.testing.assert_allclose(got, want, atol=1e-4)
    # ...but not the same model inputs: a heading-aligned network sees a turned body
    assert np.abs(shifted["serve_xyz"] - d["serve_xyz"]).max() > 0.05
    np.testing.assert_array_equal(shifted["serve_uv"], d["serve_uv"])
    r = evaluate(shifted["kp3d"], shifted, cfg)
    assert r["oks_acc_3d"] == 1.0 and r["oks_acc_2d"] == 1.0
    # the original truth in the turned frame is off by the turn
    assert evaluate(d["kp3d"], shifted, cfg)["mpjpe_3d_m"] > 0.01
