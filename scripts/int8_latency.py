"""The camera network's latency in float32 and in INT8 (its `variants.int8` file), ONNX Runtime on
the CPU, 1 and 2 intra-op threads, batch 1 and 16, interleaved, median of five runs
(BENCHMARKS.md, "INT8 camera network"). `--against B` also times bundle B's float32 camera net in
the same rounds, for a bundle whose INT8 net replaces another's float32 one.

    .venv/bin/python scripts/int8_latency.py [--bundle models/default] [--against models/default]
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


def camera(bundle: Path) -> dict:
    return json.loads((bundle / "manifest.json").read_text())["models"]["camera"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bundle", type=Path, default=Path("models/default"))
    ap.add_argument("--against", type=Path, help="another bundle whose float32 camera net is timed too")
    a = ap.parse_args()
    cam = camera(a.bundle)
    files = {"fp32": a.bundle / cam["file"], "int8": a.bundle / cam["variants"]["int8"]["file"]}
    head = "| threads | batch | fp32 ms | int8 ms | speed-up |"
    if a.against:
        other = camera(a.against)
        if other["inputs"]["image"] != cam["inputs"]["image"]:
            raise SystemExit(f"{a.against}'s camera takes {other['inputs']['image']}, not {cam['inputs']['image']}")
        files["against"] = a.against / other["file"]
        head += f" {a.against} fp32 ms | int8 against it |"
    s = cam["inputs"]["image"][-1]
    print(head + "\n" + "|---" * (head.count("|") - 1) + "|")
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
            row = f"| {threads} | {batch} | {m['fp32']:.3f} | {m['int8']:.3f} | {m['fp32'] / m['int8']:.2f}× |"
            if a.against:
                row += f" {m['against']:.3f} | {m['against'] / m['int8']:.2f}× |"
            print(row)


if __name__ == "__main__":
    main()
