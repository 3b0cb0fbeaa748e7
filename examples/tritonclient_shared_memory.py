"""One frame through a posefuse server's system shared-memory extension with Triton's own client
(`tritonclient.utils.shared_memory`), over HTTP and over gRPC: the camera image as RGB8 pixels and
the LiDAR points lie in one POSIX shared-memory region, the server writes `keypoints_3d`,
`keypoints_2d` and `scores` into another, and only the small tensors (calibration, boxes) and
`mode`/`status` travel through the socket. Each answer is checked equal to `POST /v1/poses` for
the same pixels (sent there as `image_rgb`), to float32 rounding.

    posefuse serve --system-shared-memory        # off by default (docs/KSERVE.md)
    python examples/tritonclient_shared_memory.py --url localhost:8080 --frame examples/frame.json

The server must run on the same host (it opens the regions' objects under /dev/shm). Exit status 0
when every answer matches, 1 otherwise. models-export/tests/test_kserve_client.py runs it.
"""

from __future__ import annotations

import argparse
import base64
import io
import json
import os
import sys
import warnings
from pathlib import Path

import numpy as np
import tritonclient.grpc as grpcclient
import tritonclient.http as httpclient
from PIL import Image

# tritonclient's shared-memory module imports pkg_resources, which warns that it is deprecated.
with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)
    import tritonclient.utils.shared_memory as shm
from tritonclient.utils import InferenceServerException

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tritonclient_infer import (  # noqa: E402
    DATATYPES,
    K,
    differences,
    expected_outputs,
    frame_tensors,
    v1_poses,
)

# The outputs the server writes into shared memory, with their values per keypoint.
PLACED = (("keypoints_3d", 3), ("keypoints_2d", 2), ("scores", 1))


def with_pixels(frame: dict) -> tuple[dict, np.ndarray]:
    """The frame with its JPEG/PNG replaced by the decoded RGB8 pixels (`image_rgb`), and the
    pixels as an [H, W, 3] array: the reference answer and the shared-memory one see the same
    pixels, whatever decoder decoded them."""
    pixels = np.asarray(Image.open(io.BytesIO(base64.b64decode(frame["image"]))).convert("RGB"))
    h, w, _ = pixels.shape
    rgb = {"width": w, "height": h, "b64": base64.b64encode(pixels.tobytes()).decode()}
    return {**{k: v for k, v in frame.items() if k != "image"}, "image_rgb": rgb}, pixels


class Placed:
    """An InferResult whose shared-memory outputs are read from their region (`as_numpy`)."""

    def __init__(self, result, handle, offsets: dict[str, int]):
        self.result, self.handle, self.offsets = result, handle, offsets

    def as_numpy(self, name: str):
        if name not in self.offsets:
            return self.result.as_numpy(name)
        out = self.result.get_output(name)
        shape = out["shape"] if isinstance(out, dict) else list(out.shape)
        return shm.get_contents_as_numpy(self.handle, np.float32, shape, offset=self.offsets[name])


def infer(module, client, model: str, frame: dict, pixels: np.ndarray, names: tuple[str, str],
          tag: str) -> tuple[object, dict[str, int]]:
    """One inference with the inputs and outputs in regions `names` (registered by the caller)."""
    points = next(arr for name, arr in frame_tensors(frame, image_as_base64=False) if name == "points")
    inputs = []
    for name, arr, offset in (("image_rgb", pixels, 0), ("points", points, pixels.nbytes)):
        t = module.InferInput(name, list(arr.shape), "UINT8" if arr.dtype == np.uint8 else "FP32")
        t.set_shared_memory(names[0], arr.nbytes, offset=offset)
        inputs.append(t)
    for name, arr in frame_tensors(frame, image_as_base64=False):
        if name not in ("points", "image"):
            t = module.InferInput(name, list(arr.shape), DATATYPES[arr.dtype])
            t.set_data_from_numpy(arr)
            inputs.append(t)
    m = len(frame["persons"])
    offsets, outputs, at = {}, [], 0
    for name, per_keypoint in PLACED:
        size = m * K * per_keypoint * 4
        o = module.InferRequestedOutput(name)
        o.set_shared_memory(names[1], size, offset=at)
        offsets[name], at = at, at + size
        outputs.append(o)
    outputs += [module.InferRequestedOutput(name) for name in ("mode", "status")]
    return client.infer(model, inputs, outputs=outputs, request_id=tag), offsets


def run(url: str, frame: dict, model: str = "default") -> bool:
    """Sends the frame over HTTP and gRPC through shared memory; prints each answer's comparison
    with /v1/poses, or why it failed; True when both matched."""
    reference, pixels = with_pixels(frame)
    expected = expected_outputs(reference, v1_poses(url, reference))
    print(f"/v1/poses (image_rgb): modes {expected['mode']}, status {expected['status']}")
    points = next(arr for name, arr in frame_tensors(frame, image_as_base64=False) if name == "points")
    in_size = pixels.nbytes + points.nbytes
    out_size = len(frame["persons"]) * K * sum(n for _, n in PLACED) * 4
    keys = (f"/posefuse-example-{os.getpid()}-in", f"/posefuse-example-{os.getpid()}-out")
    handles = (shm.create_shared_memory_region("in", keys[0], in_size),
               shm.create_shared_memory_region("out", keys[1], out_size))
    shm.set_shared_memory_region(handles[0], [np.ascontiguousarray(pixels), points])
    ok = True
    try:
        for label, module in (("http", httpclient), ("grpc", grpcclient)):
            client = module.InferenceServerClient(url=url)
            names = (f"{label}-in", f"{label}-out")
            try:
                client.register_system_shared_memory(names[0], keys[0], in_size)
                client.register_system_shared_memory(names[1], keys[1], out_size)
                status = client.get_system_shared_memory_status()
                result, offsets = infer(module, client, model, frame, pixels, names, label)
                wrong = differences(Placed(result, handles[1], offsets), expected)
                if wrong:
                    raise ValueError("DIFFERENT from /v1/poses: " + "; ".join(wrong))
                regions = len(status) if isinstance(status, list) else len(status.regions)
                print(f"{label} shared memory: {regions} regions registered, {in_size} bytes in, "
                      f"{out_size} bytes out: equal to /v1/poses")
            except (InferenceServerException, ValueError) as e:
                ok = False
                why = f"{e.status()} {e.message()}" if isinstance(e, InferenceServerException) else str(e)
                print(f"{label} shared memory: FAILED: {why}")
            finally:
                client.unregister_system_shared_memory()
    finally:
        for h in handles:
            shm.destroy_shared_memory_region(h)
    return ok


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", default="localhost:8080", help="the server's host:port (HTTP and gRPC)")
    parser.add_argument("--frame", type=Path, default=Path(__file__).with_name("frame.json"),
                        help="a frame with an image, in the native JSON form (default: examples/frame.json)")
    parser.add_argument("--model", default="default", help="the model (bundle) name")
    args = parser.parse_args(argv)
    ok = run(args.url, json.loads(args.frame.read_text()), args.model)
    print("all answers equal /v1/poses" if ok else "FAILED: see above")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
