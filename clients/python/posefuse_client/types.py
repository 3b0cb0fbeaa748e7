"""Typed requests and responses. Points and keypoints are numpy arrays; the JSON and protobuf forms
of the server's API (docs in the repository's README and proto/posefuse.proto) are built here."""

from __future__ import annotations

import base64
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from .errors import grpc_message_code
from .images import image_bytes

Mode = Literal["auto", "fusion", "lidar", "camera"]
MODES: tuple[str, ...] = ("auto", "fusion", "lidar", "camera")


@dataclass
class Calibration:
    """Waymo camera model: intrinsic [f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3], 4x4 camera→vehicle
    extrinsic (row-major, 16 numbers or a [4, 4] array), image width and height in pixels."""

    intrinsic: Sequence[float]
    extrinsic: Sequence[float] | np.ndarray
    width: int
    height: int

    def to_json(self) -> dict[str, Any]:
        return {
            "intrinsic": [float(v) for v in self.intrinsic],
            "extrinsic": [float(v) for v in np.asarray(self.extrinsic, dtype=np.float64).reshape(-1)],
            "width": int(self.width),
            "height": int(self.height),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Calibration:
        return cls(list(d["intrinsic"]), list(d["extrinsic"]), int(d["width"]), int(d["height"]))


@dataclass
class Box2d:
    """Centre and size in image pixels."""

    center_x: float
    center_y: float
    width: float
    height: float

    def to_json(self) -> dict[str, float]:
        return {k: float(getattr(self, k)) for k in ("center_x", "center_y", "width", "height")}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Box2d:
        return cls(d["center_x"], d["center_y"], d["width"], d["height"])


@dataclass
class Box3d:
    """Centre (vehicle frame, metres), size (length along heading, width, height) and heading (yaw
    about z, radians)."""

    center_x: float
    center_y: float
    center_z: float
    length: float
    width: float
    height: float
    heading: float

    _FIELDS = ("center_x", "center_y", "center_z", "length", "width", "height", "heading")

    def to_json(self) -> dict[str, float]:
        return {k: float(getattr(self, k)) for k in self._FIELDS}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Box3d:
        return cls(*(d[k] for k in cls._FIELDS))


@dataclass
class GroundTruth:
    """Labels for /v1/evaluate: 3D keypoints [13, 3] (vehicle frame) and/or 2D [13, 2] (pixels),
    each with a visibility mask [13]."""

    keypoints_3d: np.ndarray | None = None
    visible_3d: np.ndarray | None = None
    keypoints_2d: np.ndarray | None = None
    visible_2d: np.ndarray | None = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if self.keypoints_3d is not None:
            xyz = np.asarray(self.keypoints_3d, dtype=np.float64)
            vis = np.ones(len(xyz), bool) if self.visible_3d is None else np.asarray(self.visible_3d, bool)
            out["keypoints_3d"] = {"xyz": xyz.tolist(), "visible": vis.tolist()}
        if self.keypoints_2d is not None:
            uv = np.asarray(self.keypoints_2d, dtype=np.float64)
            vis = np.ones(len(uv), bool) if self.visible_2d is None else np.asarray(self.visible_2d, bool)
            out["keypoints_2d"] = {"uv": uv.tolist(), "visible": vis.tolist()}
        return out

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> GroundTruth:
        gt = cls()
        if "keypoints_3d" in d:
            gt.keypoints_3d = np.asarray(d["keypoints_3d"]["xyz"], dtype=np.float64).reshape(-1, 3)
            gt.visible_3d = np.asarray(d["keypoints_3d"]["visible"], dtype=bool)
        if "keypoints_2d" in d:
            gt.keypoints_2d = np.asarray(d["keypoints_2d"]["uv"], dtype=np.float64).reshape(-1, 2)
            gt.visible_2d = np.asarray(d["keypoints_2d"]["visible"], dtype=bool)
        return gt


@dataclass
class Person:
    """A person to estimate: id, 3D box, and the 2D box when known (else the projected 3D box).
    camera: in a frame with `cameras`, the name of the one to use (required with box_2d); None:
    the server takes the camera that sees the 3D box best."""

    id: str
    box_3d: Box3d
    box_2d: Box2d | None = None
    ground_truth: GroundTruth | None = None
    camera: str | None = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"id": self.id, "box_3d": self.box_3d.to_json()}
        if self.camera is not None:
            out["camera"] = self.camera
        if self.box_2d is not None:
            out["box_2d"] = self.box_2d.to_json()
        if self.ground_truth is not None:
            out["ground_truth"] = self.ground_truth.to_json()
        return out

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Person:
        return cls(
            id=d["id"],
            box_3d=Box3d.from_json(d["box_3d"]),
            box_2d=Box2d.from_json(d["box_2d"]) if d.get("box_2d") is not None else None,
            ground_truth=GroundTruth.from_json(d["ground_truth"]) if d.get("ground_truth") is not None else None,
            camera=d.get("camera"),
        )


@dataclass
class RgbPixels:
    """Decoded RGB8 pixels, sent as they are (`image_rgb`: no JPEG or PNG on either side):
    `width * height * 3` bytes, row by row from the top-left. The size must be the calibration's."""

    width: int
    height: int
    pixels: bytes

    def __post_init__(self) -> None:
        self.pixels = bytes(self.pixels)
        if len(self.pixels) != int(self.width) * int(self.height) * 3:
            raise ValueError(
                f"image_rgb: {len(self.pixels)} bytes, but {self.width}x{self.height} RGB8 pixels are "
                f"{int(self.width) * int(self.height) * 3} bytes"
            )

    @classmethod
    def from_array(cls, image: np.ndarray) -> RgbPixels:
        """The pixels of a uint8 array [H, W, 3]."""
        a = np.asarray(image)
        if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"image_rgb must be a uint8 array [H, W, 3], got {a.dtype} {a.shape}")
        return cls(a.shape[1], a.shape[0], np.ascontiguousarray(a).tobytes())

    def to_array(self) -> np.ndarray:
        """The pixels as a uint8 array [H, W, 3]."""
        return np.frombuffer(self.pixels, np.uint8).reshape(int(self.height), int(self.width), 3)

    def to_json(self) -> dict[str, Any]:
        return {"width": int(self.width), "height": int(self.height),
                "b64": base64.b64encode(self.pixels).decode("ascii")}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> RgbPixels:
        return cls(int(d["width"]), int(d["height"]), base64.b64decode(d["b64"]))


def _image_json(out: dict[str, Any], image: bytes | np.ndarray | None, image_rgb: RgbPixels | None) -> None:
    """Writes `image` (encoded) and/or `image_rgb` (raw pixels, as given) into a JSON body."""
    img = image_bytes(image)
    if img is not None:
        out["image"] = base64.b64encode(img).decode("ascii")
    if image_rgb is not None:
        out["image_rgb"] = image_rgb.to_json()


def _image_proto(message, image: bytes | np.ndarray | None, image_rgb: RgbPixels | None) -> None:
    """Sets `image` and/or `image_rgb` (with its width and height) on a PredictRequest or Camera."""
    message.image = image_bytes(image) or b""
    if image_rgb is not None:
        message.image_rgb = image_rgb.pixels
        message.image_rgb_width = int(image_rgb.width)
        message.image_rgb_height = int(image_rgb.height)


def _image_from_json(d: dict[str, Any]) -> tuple[bytes | None, RgbPixels | None]:
    image = base64.b64decode(d["image"]) if d.get("image") else None
    rgb = RgbPixels.from_json(d["image_rgb"]) if d.get("image_rgb") is not None else None
    return image, rgb


@dataclass
class Camera:
    """One camera of a frame with several: a unique name, its calibration and its image: encoded
    JPEG/PNG bytes or a uint8 array [H, W, 3] (sent as PNG) in `image`, or decoded pixels sent
    as they are in `image_rgb` (one of the two)."""

    name: str
    calibration: Calibration
    image: bytes | np.ndarray | None = None
    image_rgb: RgbPixels | None = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name}
        if self.image is None and self.image_rgb is None:
            out["image"] = ""  # the server names the camera whose image is missing
        _image_json(out, self.image, self.image_rgb)
        out["calibration"] = self.calibration.to_json()
        return out

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Camera:
        image, rgb = _image_from_json(d)
        return cls(d["name"], Calibration.from_json(d["calibration"]), image, rgb)

    def to_proto(self):
        from . import _proto as pb

        camera = pb.Camera(name=self.name, calibration=pb.Calibration(**self.calibration.to_json()))
        _image_proto(camera, self.image, self.image_rgb)
        return camera


@dataclass
class Frame:
    """One LiDAR sweep with one camera frame, or with several (`cameras`).

    calibration: the single camera's (None with `cameras`).
    points: [N, 3] x, y, z in the vehicle frame (metres); sent as little-endian float32.
    image: the single camera's encoded JPEG/PNG bytes, or a uint8 array [H, W, 3] (sent as PNG);
    None: LiDAR only (or `cameras`, or `image_rgb`).
    image_rgb: the single camera's decoded pixels instead of `image`, sent as they are (no
    re-encoding; `RgbPixels.from_array` takes a uint8 [H, W, 3] array).
    cameras: several cameras of the same instant instead of calibration and image; each person
    uses the one it names, else the one that sees it best (`PersonPose.camera` says which).
    """

    calibration: Calibration | None
    points: np.ndarray
    persons: list[Person]
    image: bytes | np.ndarray | None = None
    frame_id: str | None = None
    mode: Mode = "auto"
    cameras: list[Camera] | None = None
    image_rgb: RgbPixels | None = None

    def points_bytes(self) -> bytes:
        pts = np.asarray(self.points, dtype="<f4")
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must be [N, 3], got shape {pts.shape}")
        return np.ascontiguousarray(pts).tobytes()

    def to_json(self) -> dict[str, Any]:
        """The body of POST /v1/poses (points in the compact base64 form)."""
        out: dict[str, Any] = {}
        if self.frame_id is not None:
            out["frame_id"] = self.frame_id
        _image_json(out, self.image, self.image_rgb)
        if self.calibration is not None:
            out["calibration"] = self.calibration.to_json()
        if self.cameras:
            out["cameras"] = [c.to_json() for c in self.cameras]
        out["points"] = {"b64": base64.b64encode(self.points_bytes()).decode("ascii")}
        out["persons"] = [p.to_json() for p in self.persons]
        if self.mode != "auto":
            out["mode"] = self.mode
        return out

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Frame:
        """A frame from its JSON form (e.g. examples/frame.json); either points form is read."""
        pts = d["points"]
        if isinstance(pts, dict):
            points = np.frombuffer(base64.b64decode(pts["b64"]), dtype="<f4").reshape(-1, 3)
        else:
            points = np.asarray(pts, dtype=np.float32).reshape(-1, 3)
        image, image_rgb = _image_from_json(d)
        return cls(
            calibration=Calibration.from_json(d["calibration"]) if d.get("calibration") is not None else None,
            points=points,
            persons=[Person.from_json(p) for p in d["persons"]],
            image=image,
            image_rgb=image_rgb,
            frame_id=d.get("frame_id"),
            mode=d.get("mode", "auto"),
            cameras=[Camera.from_json(c) for c in d["cameras"]] if d.get("cameras") else None,
        )

    def to_proto(self):
        """The gRPC PredictRequest (ground truth is not part of it)."""
        from . import _proto as pb

        persons = []
        for p in self.persons:
            person = pb.Person(id=p.id, box_3d=pb.Box3d(**p.box_3d.to_json()), camera=p.camera or "")
            if p.box_2d is not None:
                person.box_2d.CopyFrom(pb.Box2d(**p.box_2d.to_json()))
            persons.append(person)
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        request = pb.PredictRequest(
            frame_id=self.frame_id or "",
            cameras=[c.to_proto() for c in self.cameras or []],
            points=self.points_bytes(),
            persons=persons,
            mode=MODES.index(self.mode),
        )
        _image_proto(request, self.image, self.image_rgb)
        if self.calibration is not None:
            request.calibration.CopyFrom(pb.Calibration(**self.calibration.to_json()))
        return request


@dataclass
class ErrorInfo:
    """An error item (batch, stream or skipped person): code, message, field."""

    code: str
    message: str
    field: str | None = None

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> ErrorInfo:
        return cls(d["code"], d["message"], d.get("field"))


@dataclass
class Facing:
    """Which way the body faces: yaw about z in the vehicle frame, radians (0 faces +x, pi/2
    faces +y), and a 0..1 confidence (from the predicted shoulders and hips)."""

    yaw: float
    confidence: float


@dataclass
class PersonPose:
    """One person's pose.

    keypoints_3d: [13, 3] vehicle frame, metres. keypoints_2d: [13, 2] image pixels, NaN where a
    keypoint does not project. scores: [13] heatmap peaks, NaN when no camera ran. camera: the
    request camera whose pixels box_2d and keypoints_2d are in (None: a single-camera frame, or
    no camera sees the person).
    """

    id: str
    mode: str
    mode_reason: str
    num_points: int
    names: list[str]
    waymo_types: list[int]
    keypoints_3d: np.ndarray
    keypoints_2d: np.ndarray
    scores: np.ndarray
    box_2d: Box2d | None = None
    facing: Facing | None = None
    camera: str | None = None

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> PersonPose:
        kps = d["keypoints"]
        nan = float("nan")
        return cls(
            id=d["id"],
            mode=d["mode"],
            mode_reason=d["mode_reason"],
            num_points=int(d["num_points"]),
            names=[k["name"] for k in kps],
            waymo_types=[int(k["waymo_type"]) for k in kps],
            keypoints_3d=np.array([k["xyz"] for k in kps], dtype=np.float64).reshape(-1, 3),
            keypoints_2d=np.array([k["uv"] if k.get("uv") is not None else (nan, nan) for k in kps],
                                  dtype=np.float64).reshape(-1, 2),
            scores=np.array([k["score"] if k.get("score") is not None else nan for k in kps], dtype=np.float64),
            box_2d=Box2d.from_json(d["box_2d"]) if d.get("box_2d") is not None else None,
            facing=Facing(float(d["facing"]["yaw"]), float(d["facing"]["confidence"])) if d.get("facing") else None,
            camera=d.get("camera"),
        )

    @classmethod
    def from_proto(cls, p) -> PersonPose:
        kps = p.keypoints
        return cls(
            id=p.id,
            mode=MODES[p.mode],
            mode_reason=p.mode_reason,
            num_points=int(p.num_points),
            names=[k.name for k in kps],
            waymo_types=[int(k.waymo_type) for k in kps],
            keypoints_3d=np.array([(k.x, k.y, k.z) for k in kps], dtype=np.float64).reshape(-1, 3),
            keypoints_2d=np.array([(k.u, k.v) for k in kps], dtype=np.float64).reshape(-1, 2),
            scores=np.array([k.score for k in kps], dtype=np.float64),
            box_2d=Box2d(p.box_2d.center_x, p.box_2d.center_y, p.box_2d.width, p.box_2d.height)
            if p.HasField("box_2d") else None,
            facing=Facing(p.facing.yaw, p.facing.confidence) if p.HasField("facing") else None,
            camera=p.camera or None,
        )


@dataclass
class SkippedPerson:
    """A requested person without a pose (e.g. no LiDAR point in its box)."""

    index: int
    id: str
    error: ErrorInfo


@dataclass
class Timings:
    decode_ms: float = 0.0
    preprocess_ms: float = 0.0
    queue_ms: float = 0.0
    inference_ms: float = 0.0
    total_ms: float = 0.0


@dataclass
class PoseResponse:
    """Poses of one frame, in request order, and the bundle that answered."""

    model_name: str
    model_version: str
    persons: list[PersonPose]
    skipped: list[SkippedPerson] = field(default_factory=list)
    timings: Timings = field(default_factory=Timings)
    frame_id: str | None = None

    def person(self, person_id: str) -> PersonPose:
        """The pose of the person with this id (KeyError when it got none)."""
        for p in self.persons:
            if p.id == person_id:
                return p
        raise KeyError(person_id)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> PoseResponse:
        return cls(
            model_name=d["model"]["name"],
            model_version=d["model"]["version"],
            persons=[PersonPose.from_json(p) for p in d["persons"]],
            skipped=[SkippedPerson(s["index"], s["id"], ErrorInfo.from_json(s["error"])) for s in d.get("skipped", [])],
            timings=Timings(**{k: float(v) for k, v in d["timings"].items() if k in Timings.__dataclass_fields__}),
            frame_id=d.get("frame_id"),
        )

    @classmethod
    def from_proto(cls, r) -> PoseResponse:
        t = r.timings
        return cls(
            model_name=r.model_name,
            model_version=r.model_version,
            persons=[PersonPose.from_proto(p) for p in r.persons],
            skipped=[SkippedPerson(int(s.index), s.id, _proto_error(s.error)) for s in r.skipped],
            timings=Timings(t.decode_ms, t.preprocess_ms, t.queue_ms, t.inference_ms, t.total_ms),
            frame_id=r.frame_id or None,
        )


@dataclass
class BatchResult:
    """One frame's result in a batch or stream: a response or an error, never both."""

    index: int
    response: PoseResponse | None = None
    error: ErrorInfo | None = None

    @property
    def ok(self) -> bool:
        return self.response is not None

    @classmethod
    def from_json(cls, d: dict[str, Any], offset: int = 0) -> BatchResult:
        return cls(
            index=int(d["index"]) + offset,
            response=PoseResponse.from_json(d["response"]) if d.get("response") is not None else None,
            error=ErrorInfo.from_json(d["error"]) if d.get("error") is not None else None,
        )

    @classmethod
    def from_proto(cls, item) -> BatchResult:
        if item.WhichOneof("result") == "response":
            return cls(int(item.index), response=PoseResponse.from_proto(item.response))
        return cls(int(item.index), error=_proto_error(item.error))


def _proto_error(e) -> ErrorInfo:
    _, field_name = grpc_message_code(e.message, e.code)
    return ErrorInfo(e.code, e.message, field_name)


def as_json(frame: Frame | dict[str, Any]) -> dict[str, Any]:
    """A request body from a Frame or from an already-JSON dict (passed through)."""
    return frame.to_json() if isinstance(frame, Frame) else frame


def as_proto(frame: Frame | dict[str, Any]):
    """A PredictRequest from a Frame or a JSON dict."""
    return (frame if isinstance(frame, Frame) else Frame.from_json(frame)).to_proto()

