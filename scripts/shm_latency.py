"""One Python client's view of a `posefuse serve --system-shared-memory` on loopback: per-request
latency over the first N simulator fixtures, three ways, interleaved frame by frame:

- `jpeg`: the fixture as it is (JPEG in base64) through `Client.predict` (POST /v1/poses);
- `pixels-json`: the decoded RGB8 pixels in the JSON body (`image_rgb`, base64) through `Client.predict`;
- `shm`: the same pixels through `SharedMemoryClient.predict`: the client copies the pixels and
  points into its region (as a client whose frames are not already there must), then sends the
  Open Inference Protocol request naming them.

Pixels are decoded (Pillow) before timing. Prints p50 and p99 per way, and the ratios to the
`--raw-ms` given (the raw ONNX Runtime p50 per frame that `posefuse bench` prints for the same
fixtures, BENCHMARKS.md).

    python scripts/shm_latency.py --url http://127.0.0.1:8080 --data data/street300_s2 -n 40 --rounds 5
"""

from __future__ import annotations

import argparse
import base64
import io
import json
import time
from pathlib import Path

import numpy as np
from PIL import Image
from posefuse_client import Client, Frame, RgbPixels, SharedMemoryClient


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", default="http://127.0.0.1:8080")
    ap.add_argument("--data", type=Path, required=True, help="simulator output directory (its requests/*.json)")
    ap.add_argument("-n", type=int, default=40, help="fixtures used")
    ap.add_argument("--rounds", type=int, default=5, help="passes over the fixtures")
    ap.add_argument("--raw-ms", type=float, help="raw ONNX Runtime p50 per frame, for the ratios")
    args = ap.parse_args()

    files = sorted((args.data / "requests").glob("*.json"))[: args.n]
    jpeg, pixels = [], []
    for p in files:
        d = json.loads(p.read_text())
        for person in d["persons"]:
            person.pop("ground_truth", None)
        jpeg.append(Frame.from_json(d))
        rgb = np.asarray(Image.open(io.BytesIO(base64.b64decode(d["image"]))).convert("RGB"))
        raw = {k: v for k, v in d.items() if k != "image"}
        pixels.append(Frame.from_json(raw | {"image_rgb": RgbPixels.from_array(rgb).to_json()}))

    times: dict[str, list[float]] = {"jpeg": [], "pixels-json": [], "shm": []}
    with Client(args.url) as http, SharedMemoryClient(args.url) as shm:
        ways = {"jpeg": lambda i: http.predict(jpeg[i]), "pixels-json": lambda i: http.predict(pixels[i]),
                "shm": lambda i: shm.predict(pixels[i])}
        for i in range(len(files)):  # warm-up
            for call in ways.values():
                call(i)
        for _ in range(args.rounds):
            for i in range(len(files)):
                for name, call in ways.items():
                    t = time.perf_counter()
                    call(i)
                    times[name].append((time.perf_counter() - t) * 1e3)
    for name, ts in times.items():
        p50, p99 = np.percentile(ts, 50), np.percentile(ts, 99)
        ratio = f" | p50 / raw {p50 / args.raw_ms:.2f}" if args.raw_ms else ""
        print(f"{name:12s} n {len(ts):4d} | p50 {p50:6.2f} ms | p99 {p99:6.2f} ms{ratio}")


if __name__ == "__main__":
    main()
