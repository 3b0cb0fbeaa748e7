"""gRPC clients (grpcio): `GrpcClient` (sync) and `AsyncGrpcClient` (grpc.aio), for the
`posefuse.v1.Posefuse` service and `grpc.health.v1` on the server's one port."""

from __future__ import annotations

from collections.abc import AsyncIterable, AsyncIterator, Iterable, Iterator
from typing import Any

import grpc
import grpc.aio

from . import _proto as pb
from .errors import PosefuseError
from .types import BatchResult, Frame, PoseResponse, as_proto

FrameLike = Frame | dict[str, Any]
# The server's default body limit (POSEFUSE_BODY_LIMIT) is 32 MiB; grpcio's default receive limit is 4 MiB.
_OPTIONS = [("grpc.max_send_message_length", 64 << 20), ("grpc.max_receive_message_length", 64 << 20)]


def _stubs(channel):
    """Callables for Predict, PredictStream and the health Check on `channel` (sync or aio)."""
    return (
        channel.unary_unary(pb.PREDICT, request_serializer=pb.PredictRequest.SerializeToString,
                            response_deserializer=pb.PredictResponse.FromString),
        channel.stream_stream(pb.PREDICT_STREAM, request_serializer=pb.PredictRequest.SerializeToString,
                              response_deserializer=pb.StreamResponse.FromString),
        channel.unary_unary(pb.HEALTH_CHECK, request_serializer=pb.HealthCheckRequest.SerializeToString,
                            response_deserializer=pb.HealthCheckResponse.FromString),
    )


def _error(e: grpc.RpcError) -> PosefuseError:
    code = e.code() if callable(getattr(e, "code", None)) else None
    details = e.details() if callable(getattr(e, "details", None)) else None
    name = code.name if code is not None else "UNKNOWN"
    if name == "UNAVAILABLE" and not (details or "").startswith("not ready:"):
        return PosefuseError("transport_error", details or str(e), grpc_status=name)
    return PosefuseError.from_grpc(name, details or "")


class GrpcClient:
    """Synchronous gRPC client. `target` is `host:port` (plaintext) or pass a ready `channel`."""

    def __init__(self, target: str = "localhost:8080", timeout: float | None = 30.0,
                 channel: grpc.Channel | None = None) -> None:
        self._channel = channel or grpc.insecure_channel(target, options=_OPTIONS)
        self._predict, self._predict_stream, self._check = _stubs(self._channel)
        self._timeout = timeout

    def __enter__(self) -> GrpcClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._channel.close()

    def predict(self, frame: FrameLike) -> PoseResponse:
        """Predict: the poses of every person of one frame."""
        try:
            return PoseResponse.from_proto(self._predict(as_proto(frame), timeout=self._timeout))
        except grpc.RpcError as e:
            raise _error(e) from e

    def predict_stream(self, frames: Iterable[FrameLike], timeout: float | None = None) -> Iterator[BatchResult]:
        """PredictStream: frames in, one result per frame out, in order, as they are answered; a
        bad frame gives a result with `error` and the stream goes on."""
        try:
            for item in self._predict_stream((as_proto(f) for f in frames), timeout=timeout):
                yield BatchResult.from_proto(item)
        except grpc.RpcError as e:
            raise _error(e) from e

    def ready(self, service: str = "") -> bool:
        """grpc.health.v1 Check: SERVING once the bundle is loaded and warmed up (as /readyz)."""
        try:
            reply = self._check(pb.HealthCheckRequest(service=service), timeout=self._timeout)
        except grpc.RpcError:
            return False
        return reply.status == pb.SERVING


class AsyncGrpcClient:
    """Asynchronous gRPC client (grpc.aio); create it inside the event loop that uses it."""

    def __init__(self, target: str = "localhost:8080", timeout: float | None = 30.0,
                 channel: grpc.aio.Channel | None = None) -> None:
        self._channel = channel or grpc.aio.insecure_channel(target, options=_OPTIONS)
        self._predict, self._predict_stream, self._check = _stubs(self._channel)
        self._timeout = timeout

    async def __aenter__(self) -> AsyncGrpcClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def close(self) -> None:
        await self._channel.close()

    async def predict(self, frame: FrameLike) -> PoseResponse:
        try:
            return PoseResponse.from_proto(await self._predict(as_proto(frame), timeout=self._timeout))
        except grpc.RpcError as e:
            raise _error(e) from e

    async def predict_stream(
        self, frames: Iterable[FrameLike] | AsyncIterable[FrameLike], timeout: float | None = None
    ) -> AsyncIterator[BatchResult]:
        """As `GrpcClient.predict_stream`; `frames` may be an async iterable."""

        async def requests():
            if isinstance(frames, AsyncIterable):
                async for f in frames:
                    yield as_proto(f)
            else:
                for f in frames:
                    yield as_proto(f)

        try:
            async for item in self._predict_stream(requests(), timeout=timeout):
                yield BatchResult.from_proto(item)
        except grpc.RpcError as e:
            raise _error(e) from e

    async def ready(self, service: str = "") -> bool:
        try:
            reply = await self._check(pb.HealthCheckRequest(service=service), timeout=self._timeout)
        except grpc.RpcError:
            return False
        return reply.status == pb.SERVING
