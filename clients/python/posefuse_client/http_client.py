"""HTTP clients (httpx): `Client` (sync) and `AsyncClient`, for the server's JSON API."""

from __future__ import annotations

import json
from collections.abc import AsyncIterable, AsyncIterator, Iterable, Iterator
from typing import Any

import httpx

from .errors import PosefuseError
from .types import BatchResult, Frame, PoseResponse, as_json

NDJSON = "application/x-ndjson"
FrameLike = Frame | dict[str, Any]


def _ndjson(frames: Iterable[FrameLike]) -> bytes:
    return b"".join(json.dumps(as_json(f), separators=(",", ":")).encode() + b"\n" for f in frames)


def _check(response: httpx.Response) -> httpx.Response:
    if response.status_code >= 400:
        raise PosefuseError.from_http(response.status_code, response.read())
    return response


def _chunks(frames: Iterable[FrameLike], size: int) -> Iterator[list[FrameLike]]:
    chunk: list[FrameLike] = []
    for f in frames:
        chunk.append(f)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


class Client:
    """Synchronous client of a posefuse server's HTTP API.

    >>> with Client("http://localhost:8080") as c:
    ...     poses = c.predict(Frame.from_json(json.load(open("examples/frame.json"))))
    """

    def __init__(self, base_url: str = "http://localhost:8080", timeout: float = 30.0, **httpx_args: Any) -> None:
        self._http = httpx.Client(base_url=base_url, timeout=timeout, **httpx_args)

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _send(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        try:
            return _check(self._http.request(method, path, **kwargs))
        except httpx.TransportError as e:
            raise PosefuseError("transport_error", f"{method} {path}: {e}") from e

    def predict(self, frame: FrameLike) -> PoseResponse:
        """POST /v1/poses: the poses of every person of one frame."""
        return PoseResponse.from_json(self._send("POST", "/v1/poses", json=as_json(frame)).json())

    def predict_batch(self, frames: Iterable[FrameLike], chunk_size: int = 64) -> Iterator[BatchResult]:
        """Streams frames through POST /v1/poses:batch (NDJSON) and yields one result per frame, in
        order, as the server answers. The iterable is read lazily, `chunk_size` frames per request,
        so an unbounded stream of frames needs bounded memory. A bad frame gives a result with
        `error`; the others are answered."""
        offset = 0
        for chunk in _chunks(frames, chunk_size):
            request = self._http.build_request(
                "POST", "/v1/poses:batch", content=_ndjson(chunk), headers={"Content-Type": NDJSON}
            )
            try:
                response = self._http.send(request, stream=True)
            except httpx.TransportError as e:
                raise PosefuseError("transport_error", f"POST /v1/poses:batch: {e}") from e
            try:
                _check(response)
                for line in response.iter_lines():
                    if line.strip():
                        yield BatchResult.from_json(json.loads(line), offset)
            finally:
                response.close()
            offset += len(chunk)

    def evaluate(self, frames: Iterable[FrameLike]) -> dict[str, Any]:
        """POST /v1/evaluate: predictions and metrics (OKS/ACC, MPJPE, ...) for frames with ground
        truth; the JSON report as a dict (`predictions`, `metrics`, `failed_frames`, ...)."""
        return self._send("POST", "/v1/evaluate", json=[as_json(f) for f in frames]).json()

    def healthy(self) -> bool:
        """GET /healthz answers 200 (the process serves)."""
        try:
            return self._http.get("/healthz").status_code == 200
        except httpx.TransportError:
            return False

    def ready(self) -> bool:
        """GET /readyz answers 200 (bundle loaded and warmed up, not draining)."""
        try:
            return self._http.get("/readyz").status_code == 200
        except httpx.TransportError:
            return False

    def models(self) -> dict[str, Any]:
        """GET /v1/models: the served bundle's manifest."""
        return self._send("GET", "/v1/models").json()

    def metrics(self) -> str:
        """GET /metrics: Prometheus text exposition."""
        return self._send("GET", "/metrics").text

    def openapi(self) -> dict[str, Any]:
        """GET /openapi.json: the request and response schemas."""
        return self._send("GET", "/openapi.json").json()


class AsyncClient:
    """Asynchronous client of a posefuse server's HTTP API (same methods as `Client`, awaited)."""

    def __init__(self, base_url: str = "http://localhost:8080", timeout: float = 30.0, **httpx_args: Any) -> None:
        self._http = httpx.AsyncClient(base_url=base_url, timeout=timeout, **httpx_args)

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _send(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        try:
            response = await self._http.request(method, path, **kwargs)
        except httpx.TransportError as e:
            raise PosefuseError("transport_error", f"{method} {path}: {e}") from e
        if response.status_code >= 400:
            raise PosefuseError.from_http(response.status_code, response.content)
        return response

    async def predict(self, frame: FrameLike) -> PoseResponse:
        return PoseResponse.from_json((await self._send("POST", "/v1/poses", json=as_json(frame))).json())

    async def predict_batch(
        self, frames: Iterable[FrameLike] | AsyncIterable[FrameLike], chunk_size: int = 64
    ) -> AsyncIterator[BatchResult]:
        """As `Client.predict_batch`; `frames` may be an async iterable."""
        offset = 0
        async for chunk in _achunks(frames, chunk_size):
            request = self._http.build_request(
                "POST", "/v1/poses:batch", content=_ndjson(chunk), headers={"Content-Type": NDJSON}
            )
            try:
                response = await self._http.send(request, stream=True)
            except httpx.TransportError as e:
                raise PosefuseError("transport_error", f"POST /v1/poses:batch: {e}") from e
            try:
                if response.status_code >= 400:
                    raise PosefuseError.from_http(response.status_code, await response.aread())
                async for line in response.aiter_lines():
                    if line.strip():
                        yield BatchResult.from_json(json.loads(line), offset)
            finally:
                await response.aclose()
            offset += len(chunk)

    async def evaluate(self, frames: Iterable[FrameLike]) -> dict[str, Any]:
        return (await self._send("POST", "/v1/evaluate", json=[as_json(f) for f in frames])).json()

    async def healthy(self) -> bool:
        try:
            return (await self._http.get("/healthz")).status_code == 200
        except httpx.TransportError:
            return False

    async def ready(self) -> bool:
        try:
            return (await self._http.get("/readyz")).status_code == 200
        except httpx.TransportError:
            return False

    async def models(self) -> dict[str, Any]:
        return (await self._send("GET", "/v1/models")).json()

    async def metrics(self) -> str:
        return (await self._send("GET", "/metrics")).text

    async def openapi(self) -> dict[str, Any]:
        return (await self._send("GET", "/openapi.json")).json()


async def _achunks(frames: Iterable[FrameLike] | AsyncIterable[FrameLike], size: int) -> AsyncIterator[list[FrameLike]]:
    chunk: list[FrameLike] = []
    if isinstance(frames, AsyncIterable):
        async for f in frames:
            chunk.append(f)
            if len(chunk) == size:
                yield chunk
                chunk = []
    else:
        for f in frames:
            chunk.append(f)
            if len(chunk) == size:
                yield chunk
                chunk = []
    if chunk:
        yield chunk
