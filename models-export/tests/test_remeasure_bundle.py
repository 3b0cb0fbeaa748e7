"""tools.remeasure_bundle: a bundle's held-out metrics re-measured under the current convention,
the old figures kept, the networks untouched."""

import json

from test_export import small_models

from posefuse_train.bundle_eval import held_out
from posefuse_train.data import read_meta
from posefuse_train.export import export_bundle
from posefuse_train.metrics import CONVENTION
from posefuse_train.shards import ShardSet
from tools import remeasure_bundle


def test_metrics_are_rewritten_under_the_convention_and_the_old_ones_kept(synthetic_sets, tmp_path):
    _, cfg = read_meta(synthetic_sets[1])
    bundle = tmp_path / "b"
    export_bundle(bundle, *small_models(cfg), cfg, trained=False)
    path = bundle / "manifest.json"
    m = json.loads(path.read_text())
    assert m["metrics"]["convention"] == CONVENTION
    # a bundle from before the convention: visible-only figures and no `convention`
    m["metrics"] = {"held_out": {"fusion": {"mpjpe_3d_m": 0.01}, "lidar": {}, "camera": {}}}
    path.write_text(json.dumps(m))
    onnx_before = {p.name: p.read_bytes() for p in bundle.glob("*.onnx")}
    args = ["--bundle", str(bundle), "--test", str(synthetic_sets[1]), "--threads", "1"]
    assert remeasure_bundle.main(args) == 0
    after = json.loads(path.read_text())
    want = held_out(bundle, ShardSet(synthetic_sets[1]), threads=1)
    assert after["metrics"]["convention"] == CONVENTION
    assert after["metrics"]["held_out"]["fusion"]["mpjpe_3d_m"] == want["fusion"]["mpjpe_3d_m"]
    # the point networks' modes also say how they score without the camera-lifted persons
    held = after["metrics"]["held_out"]
    assert {"visible", "occluded", "with_points"} <= held["lidar"]["breakdown"].keys()
    assert held["fusion"]["breakdown"]["with_points"] == want["fusion"]["breakdown"]["with_points"]
    assert "with_points" not in held["camera"]["breakdown"]
    assert after["metrics"]["previous"] == {
        "convention": "visible keypoints only",
        "held_out": {"fusion": {"mpjpe_3d_m": 0.01}, "lidar": {}, "camera": {}},
    }
    rest = lambda d: {k: v for k, v in d.items() if k != "metrics"}  # noqa: E731
    assert rest(after) == rest(m)
    assert {p.name: p.read_bytes() for p in bundle.glob("*.onnx")} == onnx_before
    # a second run keeps the first previous figures, not its own
    remeasure_bundle.main(args)
    assert json.loads(path.read_text())["metrics"]["previous"] == after["metrics"]["previous"]
