"""Re-measure a bundle's held-out metrics under the current metric convention and write them into
its manifest (nothing else changes: the networks, their hashes and the training record stay).

    python -m tools.remeasure_bundle --bundle models/default --test data/street_test

Used when the metrics' definition changes (docs/RESULTS.md, "Metric convention"); the previous
numbers are kept under `metrics.previous` with their convention, so the change can be read off the
manifest."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from posefuse_train.bundle_eval import held_out
from posefuse_train.metrics import CONVENTION
from posefuse_train.shards import ShardSet


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", required=True, type=Path)
    ap.add_argument("--test", required=True, type=Path, help="simulator or converted shards")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    path = a.bundle / "manifest.json"
    manifest = json.loads(path.read_text())
    test = ShardSet(a.test)
    t = time.time()
    metrics = held_out(a.bundle, test, threads=a.threads)
    old = manifest.get("metrics", {})
    if old.get("convention") != CONVENTION and old.get("held_out"):
        previous = {
            "convention": old.get("convention", "visible keypoints only"),
            "held_out": old["held_out"],
        }
    else:
        previous = old.get("previous")
    manifest["metrics"] = {"held_out": metrics, "convention": CONVENTION}
    if previous:
        manifest["metrics"]["previous"] = previous
    path.write_text(json.dumps(manifest, indent=2) + "\n")
    pct = lambda v: f"{100 * (v or 0):.2f}"  # noqa: E731
    for mode, m in metrics.items():
        print(
            f"{mode:6s}: OKS/ACC@3D {pct(m['oks_acc_3d'])} %, MPJPE {pct(m['mpjpe_3d_m'])} cm, "
            f"OKS/ACC@2D {pct(m['oks_acc_2d'])} % ({len(test)} persons, {time.time() - t:.0f} s)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
