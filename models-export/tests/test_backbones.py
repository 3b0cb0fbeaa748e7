import json

import pytest

from experiments.backbones import main


def test_candidates_train_for_their_own_epochs(synthetic_sets, tmp_path):
    train, test = synthetic_sets
    out = tmp_path / "b"
    main(
        ["--train", str(train), "--test", str(test), "--out", str(out), "--latency-only", ""]
        + ["--candidates", "resnet18-w16:16:2,resnet18-w16:8", "--epochs", "1"]
    )
    summary = json.loads((out / "backbones.json").read_text())
    # 96 persons, batch 64: one step per epoch; a step is 64 of the 96 persons
    assert [r["epochs"] for r in summary["rows"]] == [pytest.approx(2 * 64 / 96), pytest.approx(64 / 96)]
    assert [r["deconv_channels"] for r in summary["rows"]] == [16, 8]
    assert summary["minutes"] == 0.0 and summary["command"].startswith("python -m experiments.backbones ")
