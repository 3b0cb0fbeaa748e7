"""The gRPC messages and method paths, built at import time from the committed descriptor of
proto/posefuse.proto (posefuse.binpb) and from a two-message description of grpc.health.v1, in a
private descriptor pool (so they never clash with other generated code in the same process)."""

from __future__ import annotations

from importlib import resources

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

_pool = descriptor_pool.DescriptorPool()
_set = descriptor_pb2.FileDescriptorSet.FromString(
    resources.files(__package__).joinpath("posefuse.binpb").read_bytes()
)
for _file in _set.file:
    _pool.Add(_file)


def _health_file() -> descriptor_pb2.FileDescriptorProto:
    """grpc.health.v1: HealthCheckRequest {string service = 1}, HealthCheckResponse {ServingStatus status = 1}."""
    f = descriptor_pb2.FileDescriptorProto(
        name="posefuse_client/health.proto", package="grpc.health.v1", syntax="proto3"
    )
    request = f.message_type.add(name="HealthCheckRequest")
    request.field.add(name="service", number=1, type=descriptor_pb2.FieldDescriptorProto.TYPE_STRING,
                      label=descriptor_pb2.FieldDescriptorProto.LABEL_OPTIONAL)
    response = f.message_type.add(name="HealthCheckResponse")
    status = response.enum_type.add(name="ServingStatus")
    for number, name in enumerate(["UNKNOWN", "SERVING", "NOT_SERVING", "SERVICE_UNKNOWN"]):
        status.value.add(name=name, number=number)
    response.field.add(name="status", number=1, type=descriptor_pb2.FieldDescriptorProto.TYPE_ENUM,
                       type_name=".grpc.health.v1.HealthCheckResponse.ServingStatus",
                       label=descriptor_pb2.FieldDescriptorProto.LABEL_OPTIONAL)
    return f


_pool.Add(_health_file())


def _message(name: str):
    return message_factory.GetMessageClass(_pool.FindMessageTypeByName(name))


FILE = _pool.FindFileByName("posefuse.proto")
Calibration = _message("posefuse.v1.Calibration")
Box2d = _message("posefuse.v1.Box2d")
Box3d = _message("posefuse.v1.Box3d")
Person = _message("posefuse.v1.Person")
Camera = _message("posefuse.v1.Camera")
PredictRequest = _message("posefuse.v1.PredictRequest")
PredictResponse = _message("posefuse.v1.PredictResponse")
StreamResponse = _message("posefuse.v1.StreamResponse")
HealthCheckRequest = _message("grpc.health.v1.HealthCheckRequest")
HealthCheckResponse = _message("grpc.health.v1.HealthCheckResponse")
SERVING = 1

PREDICT = "/posefuse.v1.Posefuse/Predict"
PREDICT_STREAM = "/posefuse.v1.Posefuse/PredictStream"
HEALTH_CHECK = "/grpc.health.v1.Health/Check"
