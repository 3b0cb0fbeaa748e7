"""experiments.by_range --bundle: a bundle served per range band, and the fusion net's lead over
the LiDAR-only one paired person by person."""

import json

import numpy as np
import pytest
from test_export import small_models

from experiments.by_range import main, parse_bands
from posefuse_train import bundle_eval
from posefuse_train.bundle_eval import held_out
from posefuse_train.data import load, read_meta
from posefuse_train.export import export_bundle
from posefuse_train.keypoints import PARTS
from posefuse_train.shards import ShardSet


def wrists(report: dict) -> float:
    return float(np.mean([report["per_keypoint_oks_3d"][k]["oks"] for k in PARTS["wrist"]]))


def test_one_band_over_every_range_is_the_held_out_evaluation(synthetic_sets, tmp_path, monkeypatch):
    _, cfg = read_meta(synthetic_sets[1])
    served = bundle_eval.served_answers

    def near_the_labels(*args, **kwargs):
        # Untrained nets score 0 % everywhere; answers a few centimetres from the labels score
        # something, differently for each person, and better for fusion than for LiDAR-only.
        answers, data, cfg = served(*args, **kwargs)
        rng = np.random.default_rng(0)
        for mode, sigma in (("fusion", 0.03), ("lidar", 0.06)):
            answers[mode] = data["kp3d"] + rng.normal(0, sigma, data["kp3d"].shape).astype(np.float32)
        return answers, data, cfg

    monkeypatch.setattr(bundle_eval, "served_answers", near_the_labels)
    bundle = tmp_path / "b"
    export_bundle(bundle, *small_models(cfg), cfg, trained=False)
    range_m = load(synthetic_sets[1])[0]["range_m"]
    mid = float(np.sort(range_m)[len(range_m) // 2])  # a person of the set sits on the boundary
    out = tmp_path / "by_range.json"
    main(
        ["--bundle", str(bundle), "--test", str(synthetic_sets[1]), "--bands", f"0-{mid},{mid}-1000,0-1000"]
        + ["--json", str(out)]
    )
    near, far, every = json.loads(out.read_text())
    assert (near["persons"], far["persons"]) == (int((range_m < mid).sum()), int((range_m >= mid).sum()))
    assert every["persons"] == len(range_m)
    want = held_out(bundle, ShardSet(synthetic_sets[1]))
    for mode in ("fusion", "lidar", "camera"):
        assert every[mode]["oks_acc_3d"] == pytest.approx(want[mode]["oks_acc_3d"], abs=1e-12)
        assert every[mode]["mpjpe_3d_m"] == pytest.approx(want[mode]["mpjpe_3d_m"], abs=1e-12)
        assert every[mode]["wrist"] == pytest.approx(wrists(want[mode]), abs=1e-12)
    # The paired lead is the difference of the two modes' OKS@3D, with a standard error beside it.
    lead = every["fusion_lead"]
    assert lead["oks_acc_3d"] == pytest.approx(
        want["fusion"]["oks_acc_3d"] - want["lidar"]["oks_acc_3d"], abs=1e-12
    )
    assert lead["wrist"] == pytest.approx(wrists(want["fusion"]) - wrists(want["lidar"]), abs=1e-12)
    assert lead["se"] is not None and 0 < lead["se"] < lead["oks_acc_3d"]
    assert lead["oks_acc_3d"] > 0 and lead["wrist"] > 0 and every["fusion"]["oks_acc_3d"] < 1
    assert near["fusion"] != far["fusion"] and near["fusion_lead"] != far["fusion_lead"]


def test_bands_must_run_from_low_to_high():
    assert parse_bands("3-10,10-20.5") == ((3.0, 10.0), (10.0, 20.5))
    for bad in ("10-3", "3-10-20", "5-5"):
        with pytest.raises(SystemExit, match="--bands"):
            parse_bands(bad)
