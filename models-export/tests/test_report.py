import numpy as np

from posefuse_train.ablation import degrade_lidar
from posefuse_train.report import table3

METRICS = {"oks_acc_3d": 0.5, "mpjpe_3d_m": 0.1, "oks_acc_2d": 0.9, "pck_3d_10cm": 0.5, "pem_3d_m": 0.1}


def test_table3_names_rows_that_come_from_a_separate_run():
    cfg = {"seg": True, "fusion": False, "depth_correction": True}
    rows = {
        "lidar_reg_seg": {"config": {**cfg, "depth_correction": False}, "metrics": METRICS},
        "lidar_reg_seg_depth": {"config": cfg, "metrics": METRICS, "separate_run": "python -m x --rows y"},
    }
    md = table3(rows)
    assert md.count("eq. 1 + depth correction") == 1
    assert "Row `lidar_reg_seg_depth` was trained in a separate run: `python -m x --rows y`." in md
    assert md.count("separate run") == 1


def test_degrade_lidar_adds_noise_of_the_given_scale_to_every_point_array():
    train = {"points_xyz": np.zeros((50, 40, 3), np.float32)}
    test = {"points_xyz": np.zeros((20, 40, 3), np.float32), "serve_xyz": np.ones((20, 16, 3), np.float32)}
    degrade_lidar(train, test, 0.05)
    for arr, base in ((train["points_xyz"], 0.0), (test["points_xyz"], 0.0), (test["serve_xyz"], 1.0)):
        assert arr.dtype == np.float32
        assert abs(float((arr - base).std()) - 0.05) < 0.005
        assert abs(float((arr - base).mean())) < 0.005
