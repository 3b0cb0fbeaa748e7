"""The camera network's latency in float32 and in INT8 (its `variants.int8` file), ONNX Runtime on
the CPU, 1 and 2 intra-op threads, batch 1 and 16, interleaved, median of five runs
(BENCHMARKS.md, "INT8 camera network").

    .venv/bin/python scripts/int8_latency.py [--bundle models/default]
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort


def session(path: Path, threads: int) -> ort.InferenceSession:
    o = ort.SessionOptions()
    o.intra_op_num_threads = threads
    o.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), o, providers=["CPUExecutionProvider"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bundle", type=Path, default=Path("models/default"))
    a = ap.parse_args()
    cam = json.loads((a.bundle / "manifest.json").read_text())["models"]["camera"]
    files = {"fp32": a.bundle / cam["file"], "int8": a.bundle / cam["variants"]["int8"]["file"]}
    s = cam["inputs"]["image"][-1]
    print("| threads | batch | fp32 ms | int8 ms | speed-up |\n|---|---|---|---|---|")
    for threads in (1, 2):
        sessions = {k: session(f, threads) for k, f in files.items()}
        for batch in (1, 16):
            x = np.random.default_rng(0).normal(size=(batch, 3, s, s)).astype(np.float32)
            n = 400 if batch == 1 else 40
            for sess in sessions.values():
                for _ in range(20):
                    sess.run(None, {"image": x})
            runs = {k: [] for k in sessions}
            for _ in range(5):
                for k, sess in sessions.items():
                    t = time.perf_counter()
                    for _ in range(n):
                        sess.run(None, {"image": x})
                    runs[k].append((time.perf_counter() - t) / n * 1000)
            m = {k: float(np.median(v)) for k, v in runs.items()}
            print(f"| {threads} | {batch} | {m['fp32']:.3f} | {m['int8']:.3f} | {m['fp32'] / m['int8']:.2f}× |")


if __name__ == "__main__":
    main()
