import numpy as np

from experiments.ablation import degrade_lidar
from experiments.report import (
    bundle_source,
    default_bundle_section,
    heading_error_table,
    paper_recipe_section,
    street_section,
    table3,
)
from posefuse_train.keypoints import NAMES

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


def test_paper_recipe_rows_merge_runs_in_the_papers_order_and_cite_each_command():
    cfg = {"seg": False, "fusion": False, "rotate_deg": 180.0}
    run_a = {
        "command": "python -m a",
        "wall_s": 600.0,
        "rows": {
            "camera": {},
            "fusion_reg_seg": {"config": {**cfg, "seg": True, "fusion": True}, "metrics": METRICS},
        },
    }
    run_b = {
        "command": "python -m b",
        "wall_s": 60.0,
        "rows": {"lidar_reg": {"config": cfg, "metrics": METRICS}},
    }
    md = "\n".join(paper_recipe_section([run_a, run_b]))
    assert "±180°" in md
    # the paper's order (lidar_reg before fusion_reg_seg) and the paper's numbers beside ours
    assert md.index("59.10%") < md.index("63.14%")
    assert "- `python -m a` (10.0 min)" in md and "- `python -m b` (1.0 min)" in md


def test_heading_error_table_has_a_row_per_error_and_a_column_per_model():
    cell = {"oks_acc_3d": 0.5, "mpjpe_3d_m": 0.1, "left_right_swap_rate": 0.25}
    md = heading_error_table(
        [{"error_deg": 0.0, "r:a": cell, "r:b": cell}, {"error_deg": 180.0, "r:a": cell, "r:b": cell}]
    )
    lines = md.splitlines()
    assert len(lines) == 4 and lines[3].startswith("| 180°")
    assert "`r:a` OKS@3D" in lines[0] and "`r:b` OKS@3D" in lines[0]
    assert lines[2].count("50.00% / 10.00 cm / 25.00%") == 2


def test_paper_recipe_rows_of_another_seed_get_their_own_table():
    cfg = {"seg": False, "fusion": False, "rotate_deg": 180.0}
    run = lambda seed, cmd: {  # noqa: E731
        "command": cmd,
        "wall_s": 60.0,
        "rows": {"lidar_reg": {"config": {**cfg, "seed": seed}, "metrics": METRICS}},
    }
    md = "\n".join(paper_recipe_section([run(0, "a"), run(1, "b")]))
    assert md.index("Point-net seed 0:") < md.index("Point-net seed 1:")
    assert md.count("| ✓ |  |  | eq. 1 |") == 2


def test_street_section_groups_runs_by_rotation_and_seed_and_states_each_difference():
    def metrics(oks3d, mpjpe, wrist):
        wrists = [i for i, name in enumerate(NAMES) if name.endswith("wrist")]
        per_kp = [{"name": n, "oks": wrist if i in wrists else 0.5} for i, n in enumerate(NAMES)]
        return METRICS | {
            "oks_acc_3d": oks3d,
            "mpjpe_3d_m": mpjpe,
            "per_keypoint_oks_3d": per_kp,
            "per_keypoint_oks_2d": per_kp,
        }

    def run(command, seed, rot, lidar, fusion):
        cfg = {"seg": True, "fusion": False, "rotate_deg": rot, "seed": seed}
        return {
            "command": command,
            "wall_s": 120.0,
            "train": {"path": "data/street_train", "count": 20000},
            "test": {"path": "data/street_test", "count": 2000},
            "label_quality": {"eq1": {"mean_error_m": 0.0778, "labels": 10}},
            "rows": {
                "camera": {"metrics": metrics(0.2, 0.2, 0.5)},
                "lidar_reg_seg": {"config": cfg, "metrics": metrics(*lidar)},
                "fusion_reg_seg": {"config": {**cfg, "fusion": True}, "metrics": metrics(*fusion)},
            },
        }

    runs = [
        run("python -m street", 0, 180.0, (0.40, 0.125, 0.30), (0.43, 0.121, 0.40)),
        run("python -m street --seed 1", 1, 180.0, (0.41, 0.124, 0.30), (0.42, 0.122, 0.35)),
        run("python -m street --rotate-deg 20", 0, 20.0, (0.60, 0.09, 0.5), (0.60, 0.09, 0.5)),
    ]
    md = "\n".join(street_section(runs))
    assert "## The street profile" in md and "eq1 7.78 cm" in md
    # a table per (rotation, seed), the paper's ±180° first, and none merged over another
    tables = [line for line in md.splitlines() if line.startswith("Rotation ±")]
    assert tables == [
        "Rotation ±180° about z, point-net seed 0:",
        "Rotation ±180° about z, point-net seed 1:",
        "Rotation ±20° about z, point-net seed 0:",
    ]
    assert md.count("| ✓ | ✓ |") == 6
    diffs = [line for line in md.splitlines() if line.startswith("| multi-modal − LiDAR-only, reg + seg")]
    assert diffs == [
        "| multi-modal − LiDAR-only, reg + seg | ±180° | 0 | +3.00 | -0.40 cm | +0.00 | +10.00 "
        "| +3.56 / -0.48 cm / +5.41 / +16.60 |",
        "| multi-modal − LiDAR-only, reg + seg | ±180° | 1 | +1.00 | -0.20 cm | +0.00 | +5.00 "
        "| +3.56 / -0.48 cm / +5.41 / +16.60 |",
        "| multi-modal − LiDAR-only, reg + seg | ±20° | 0 | +0.00 | +0.00 cm | +0.00 | +0.00 "
        "| +3.56 / -0.48 cm / +5.41 / +16.60 |",
    ]
    # per keypoint from the first group, beside the paper's wrist numbers
    wrist = next(line for line in md.splitlines() if line.startswith("| wrist"))
    assert "45.99%" in wrist and "30.37%" in wrist and "46.97%" in wrist and "40.00%" in wrist
    assert "- `python -m street --seed 1` (2.0 min)" in md


def test_the_default_bundle_section_names_the_latest_run_that_wrote_the_bundle():
    bundle = {"path": "models/default", "size_mb": 5.3, "fusion_row": "f", "lidar_row": "l"}
    main = {"command": "python -m main", "bundle": bundle}
    street = {
        "command": "python -m street --bundle models/default",
        "train": {"path": "data/street_train"},
        "test": {"path": "data/street_test"},
        "bundle": {**bundle, "fusion_row": "fusion_reg_seg_depth"},
    }
    assert bundle_source(main, []) is main
    assert bundle_source(main, [street, {"command": "no bundle"}]) is street
    assert bundle_source({"command": "none"}, []) is None
    md = "\n".join(default_bundle_section(street, main=False))
    assert "written by `python -m street --bundle models/default`, trained on `data/street_train`" in md
    assert "fusion model from row `fusion_reg_seg_depth`" in md
    assert "written by this ablation" in "\n".join(default_bundle_section(main))
