"""posefuse-client: typed Python clients (HTTP and gRPC, sync and async) for a posefuse server."""

from .errors import PosefuseError
from .grpc_client import AsyncGrpcClient, GrpcClient
from .http_client import AsyncClient, Client
from .images import encode_jpeg, encode_png
from .shared_memory import SharedMemoryClient, TensorPoses
from .types import (
    BatchResult,
    Box2d,
    Box3d,
    Calibration,
    Camera,
    ErrorInfo,
    Facing,
    Frame,
    GroundTruth,
    Person,
    PersonPose,
    PoseResponse,
    RgbPixels,
    SkippedPerson,
    Timings,
)

__version__ = "0.1.0"
__all__ = [
    "AsyncClient",
    "AsyncGrpcClient",
    "BatchResult",
    "Box2d",
    "Box3d",
    "Calibration",
    "Camera",
    "Client",
    "ErrorInfo",
    "Frame",
    "GrpcClient",
    "GroundTruth",
    "Person",
    "Facing",
    "PersonPose",
    "PoseResponse",
    "PosefuseError",
    "RgbPixels",
    "SharedMemoryClient",
    "SkippedPerson",
    "TensorPoses",
    "Timings",
    "encode_jpeg",
    "encode_png",
]
