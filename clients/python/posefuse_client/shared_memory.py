"""`SharedMemoryClient`: frames to a server on the same host through KServe's system shared-memory
extension (docs/KSERVE.md, "System shared memory"). The client owns one POSIX shared-memory
region (the standard library's `multiprocessing.shared_memory`), registers it with the server,
and for each frame writes the decoded RGB8 pixels and the LiDAR points into it; the request names
them, so only the calibration, the boxes and the answer cross the socket. The server must run on
the same host with `--system-shared-memory`.
"""

from __future__ import annotations

import json
import os
import secrets
from dataclasses import dataclass
from multiprocessing import shared_memory
from typing import Any

import httpx
import numpy as np

from .errors import PosefuseError, grpc_message_code
from .types import Frame

K = 13  # keypoints per person


@dataclass
class TensorPoses:
    """One frame's answer as the Open Inference Protocol's outputs: row i is person i of the
    request. A person the sensors could not answer keeps its row, NaN, with mode `none` and its
    error code as status."""

    ids: list[str]
    keypoints_3d: np.ndarray  # [M, 13, 3] vehicle frame, metres
    keypoints_2d: np.ndarray  # [M, 13, 2] pixels
    scores: np.ndarray  # [M, 13] heatmap peaks; NaN for LiDAR-only poses
    mode: list[str]  # fusion, lidar, camera or none
    status: list[str]  # ok, or why the person got no pose
    num_points: np.ndarray  # [M] LiDAR points in the box; -1 for a skipped person


def _floats(data: list[Any], shape: list[int]) -> np.ndarray:
    # JSON has no NaN: the server writes null.
    return np.array([np.nan if v is None else v for v in data], np.float32).reshape(shape)


class SharedMemoryClient:
    """Predicts frames through one shared-memory region of `capacity` bytes (pixels and points
    of one frame at a time: not for use from several threads at once).

    >>> with SharedMemoryClient("http://localhost:8080") as c:
    ...     poses = c.predict(frame)   # frame.image_rgb, or frame.image as a uint8 [H, W, 3] array
    """

    def __init__(self, base_url: str = "http://localhost:8080", model: str = "default",
                 capacity: int = 32 << 20, timeout: float = 30.0, **httpx_args: Any) -> None:
        self._http = httpx.Client(base_url=base_url, timeout=timeout, **httpx_args)
        self.model = model
        self.region = f"posefuse-client-{os.getpid()}-{secrets.token_hex(4)}"
        self._shm = shared_memory.SharedMemory(name=self.region, create=True, size=capacity)
        self.capacity = capacity
        try:
            self._post(f"/v2/systemsharedmemory/region/{self.region}/register",
                       {"key": f"/{self._shm.name}", "offset": 0, "byte_size": capacity})
        except BaseException:
            self._release()
            raise

    def __enter__(self) -> SharedMemoryClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Unregisters the region, removes it and closes the connection."""
        try:
            self._post(f"/v2/systemsharedmemory/region/{self.region}/unregister", None)
        finally:
            self._release()
            self._http.close()

    def _release(self) -> None:
        self._shm.close()
        self._shm.unlink()

    def _post(self, path: str, body: dict[str, Any] | None) -> dict[str, Any]:
        try:
            r = self._http.post(path, content=b"" if body is None else json.dumps(body).encode(),
                                headers={"content-type": "application/json"})
        except httpx.TransportError as e:
            raise PosefuseError("transport_error", f"POST {path}: {e}") from e
        if r.status_code >= 400:
            try:
                message = str(r.json()["error"])
            except (ValueError, KeyError, TypeError):
                message = r.text[:500] or f"HTTP {r.status_code}"
            code, field = grpc_message_code(message, f"http_{r.status_code}")
            raise PosefuseError(code, message, field, http_status=r.status_code)
        return r.json()

    def predict(self, frame: Frame | dict[str, Any]) -> TensorPoses:
        """The poses of the frame's persons. The frame's camera image must be pixels
        (`image_rgb`, or `image` as a uint8 [H, W, 3] array): the server reads them as they are."""
        f = frame if isinstance(frame, Frame) else Frame.from_json(frame)
        if f.cameras or f.calibration is None:
            raise ValueError("the Open Inference Protocol carries one camera: give `calibration`, not `cameras`")
        if f.image_rgb is not None:
            pixels, (w, h) = f.image_rgb.pixels, (int(f.image_rgb.width), int(f.image_rgb.height))
        elif isinstance(f.image, np.ndarray) and f.image.dtype == np.uint8 and f.image.ndim == 3:
            pixels, (h, w) = np.ascontiguousarray(f.image).tobytes(), f.image.shape[:2]
        else:
            raise ValueError("shared memory carries pixels: give `image_rgb` or `image` as a uint8 [H, W, 3] array")
        points = f.points_bytes()
        if len(pixels) + len(points) > self.capacity:
            raise ValueError(f"{len(pixels) + len(points)} bytes of pixels and points exceed the region's "
                             f"{self.capacity} (SharedMemoryClient(capacity=...))")
        self._shm.buf[: len(pixels)] = pixels
        self._shm.buf[len(pixels): len(pixels) + len(points)] = points
        r = self._post(f"/v2/models/{self.model}/infer", self._request(f, len(pixels), len(points), w, h))
        out = {o["name"]: o for o in r["outputs"]}
        m = len(f.persons)
        return TensorPoses(
            ids=[p.id for p in f.persons],
            keypoints_3d=_floats(out["keypoints_3d"]["data"], [m, K, 3]),
            keypoints_2d=_floats(out["keypoints_2d"]["data"], [m, K, 2]),
            scores=_floats(out["scores"]["data"], [m, K]),
            mode=list(out["mode"]["data"]),
            status=list(out["status"]["data"]),
            num_points=np.array(out["num_points"]["data"], np.int32),
        )

    def _request(self, f: Frame, pixel_bytes: int, point_bytes: int, w: int, h: int) -> dict[str, Any]:
        c = f.calibration.to_json()
        m = len(f.persons)
        b3 = [v for p in f.persons for v in p.box_3d.to_json().values()]
        b2 = [v for p in f.persons
              for v in (p.box_2d.to_json().values() if p.box_2d is not None else [None] * 4)]

        def shm(size: int, offset: int) -> dict[str, Any]:
            return {"shared_memory_region": self.region, "shared_memory_byte_size": size,
                    "shared_memory_offset": offset}

        inputs = [
            {"name": "image_rgb", "datatype": "UINT8", "shape": [h, w, 3], "parameters": shm(pixel_bytes, 0)},
            {"name": "points", "datatype": "FP32", "shape": [point_bytes // 12, 3],
             "parameters": shm(point_bytes, pixel_bytes)},
            {"name": "calibration_intrinsic", "datatype": "FP64", "shape": [len(c["intrinsic"])],
             "data": c["intrinsic"]},
            {"name": "calibration_extrinsic", "datatype": "FP64", "shape": [16], "data": c["extrinsic"]},
            {"name": "image_size", "datatype": "INT32", "shape": [2], "data": [c["width"], c["height"]]},
            {"name": "boxes_3d", "datatype": "FP64", "shape": [m, 7], "data": b3},
            {"name": "boxes_2d", "datatype": "FP64", "shape": [m, 4], "data": b2},
            {"name": "person_ids", "datatype": "BYTES", "shape": [m], "data": [p.id for p in f.persons]},
            {"name": "mode", "datatype": "BYTES", "shape": [1], "data": [f.mode]},
        ]
        body: dict[str, Any] = {"inputs": inputs}
        if f.frame_id is not None:
            body["id"] = f.frame_id
        return body
