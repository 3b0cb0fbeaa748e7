import json

import pytest

from experiments import profile
from posefuse_train.keypoints import NAMES, PARTS


def per_keypoint(values: dict, other: float = 0.6) -> list[dict]:
    """Per-keypoint OKS with the left and right keypoints of a part `values[part]` apart."""
    out = [None] * len(NAMES)
    for part, idx in PARTS.items():
        sides = values.get(part, (other, other))
        for n, i in enumerate(idx):
            out[i] = {"name": NAMES[i], "oks": sides[n]}
    return out


def metrics() -> dict:
    return {
        "oks_acc_3d": 0.55,
        "oks_acc_2d": 0.8,
        # 3D: wrists 0.4 and 0.6 (mean 0.5), elbows 0.7, hips 1
        "per_keypoint_oks_3d": per_keypoint({"wrist": (0.4, 0.6), "hip": (1.0, 1.0), "elbow": (0.7, 0.7)}),
        # 2D: wrists 0.72, hips 0.9 -> 0.8
        "per_keypoint_oks_2d": per_keypoint({"wrist": (0.72, 0.72), "hip": (0.9, 0.9)}),
    }


def test_ratios_are_left_right_means_over_the_hips():
    m = metrics()
    assert profile.ratios(profile.run_profile(m, "3D")) == pytest.approx([0.5, 0.7, 0.6, 0.6])
    assert profile.ratios(profile.run_profile(m, "2D"))[0] == pytest.approx(0.8)
    assert profile.ratios({"hip": 0.0, "wrist": 0.5, "elbow": None, "knee": 1, "ankle": 1}) == [None] * 4


def test_the_paper_rows_are_table_2s_lidar_column_in_each_dimension():
    assert profile.ratios(profile.paper_profile("3D"))[:2] == pytest.approx([30.37 / 79.42, 66.61 / 79.42])
    assert profile.ratios(profile.paper_profile("2D"))[:2] == pytest.approx([64.10 / 90.33, 78.72 / 90.33])


def test_render_has_a_line_per_run_and_dimension_then_the_papers(tmp_path, capsys):
    run = tmp_path / "abl"
    run.mkdir()
    (run / "results.json").write_text(json.dumps({"rows": {"lidar_reg_seg_depth": {"metrics": metrics()}}}))
    profile.main([str(run)])
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[2] == "| abl | 3D | 55.00 | 50.0 | 100.0 | 0.50 | 0.70 | 0.60 | 0.60 |"
    assert lines[3] == "| paper, LiDAR-only | 3D | 59.58 | 30.4 | 79.4 | 0.38 | 0.84 | 0.98 | 0.87 |"
    assert lines[4].startswith("| abl | 2D | 80.00 | 72.0 | 90.0 | 0.80 |")
    assert lines[5].startswith("| paper, LiDAR-only | 2D | 77.53 | 64.1 | 90.3 | 0.71 | 0.87 |")
    with pytest.raises(SystemExit, match="no row fusion_reg"):
        profile.main([str(run), "--row", "fusion_reg"])


def test_a_run_is_scored_on_another_set_with_its_own_row(synthetic_sets, tmp_path, monkeypatch, capsys):
    test_dir = synthetic_sets[1]
    asked = []

    def truth(run, rows, test, cfg):
        asked.append((run, rows, len(test["kp3d"])))
        return {rows[0]: test["kp3d"]}

    monkeypatch.setattr(profile, "run_predictions", truth)
    profile.main([str(tmp_path / "abl"), "--test", str(test_dir), "--row", "lidar_reg"])
    lines = capsys.readouterr().out.strip().splitlines()
    assert asked == [(tmp_path / "abl", ["lidar_reg"], len(profile.data_mod.load(test_dir)[0]["kp3d"]))]
    assert lines[2] == f"| abl on {test_dir.name} | 3D | 100.00 | 100.0 | 100.0 | 1.00 | 1.00 | 1.00 | 1.00 |"
