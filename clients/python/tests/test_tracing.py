"""Following a request, checked with code nobody here wrote: OpenTelemetry's W3C trace-context
propagator makes and reads the `traceparent` headers, gRPC's own client reads the metadata, and
Prometheus's text-format parser reads /metrics."""

import grpc
import httpx
from opentelemetry import trace
from opentelemetry.trace import NonRecordingSpan, SpanContext, TraceFlags
from opentelemetry.trace.propagation.tracecontext import TraceContextTextMapPropagator
from prometheus_client.parser import text_string_to_metric_families

from posefuse_client import _proto as pb

PROPAGATOR = TraceContextTextMapPropagator()
TRACE_ID = 0x0AF7651916CD43DD8448EB211C80319C
CALLER_SPAN = 0xB7AD6B7169203331


def caller_headers() -> dict:
    """The headers an OpenTelemetry-instrumented caller sends from inside its sampled span."""
    ctx = SpanContext(TRACE_ID, CALLER_SPAN, is_remote=False, trace_flags=TraceFlags(TraceFlags.SAMPLED))
    carrier: dict = {}
    PROPAGATOR.inject(carrier, context=trace.set_span_in_context(NonRecordingSpan(ctx)))
    return carrier


def server_span(headers) -> SpanContext:
    """The span context the server's answer names, as OpenTelemetry reads it."""
    got = trace.get_current_span(PROPAGATOR.extract({"traceparent": headers["traceparent"]})).get_span_context()
    assert got.is_valid, headers["traceparent"]
    return got


def test_http_continues_the_callers_trace_and_echoes_the_request_id(server, frame_json):
    headers = {**caller_headers(), "x-request-id": "py-http-1"}
    r = httpx.post(f"{server.http_url}/v1/poses", json=frame_json, headers=headers, timeout=30)
    assert r.status_code == 200
    assert r.headers["x-request-id"] == "py-http-1"
    span = server_span(r.headers)
    assert span.trace_id == TRACE_ID and span.span_id != CALLER_SPAN
    assert span.trace_flags.sampled

    alone = httpx.get(f"{server.http_url}/healthz", timeout=10)
    started = server_span(alone.headers)
    assert started.trace_id != TRACE_ID and not started.trace_flags.sampled
    assert alone.headers["x-request-id"] == format(started.trace_id, "032x")


def test_grpc_metadata_carries_the_same(server, frame_json):
    metadata = tuple((k, v) for k, v in {**caller_headers(), "x-request-id": "py-grpc-1"}.items())
    with grpc.insecure_channel(server.grpc_target) as channel:
        predict = channel.unary_unary(pb.PREDICT, request_serializer=pb.PredictRequest.SerializeToString,
                                      response_deserializer=pb.PredictResponse.FromString)
        try:
            predict(pb.PredictRequest(), metadata=metadata, timeout=30)
            raise AssertionError("an empty frame was answered")
        except grpc.RpcError as e:
            assert e.code() == grpc.StatusCode.INVALID_ARGUMENT
            answered = dict(e.initial_metadata()) | dict(e.trailing_metadata())
    assert answered["x-request-id"] == "py-grpc-1"
    assert server_span(answered).trace_id == TRACE_ID


def test_metrics_parse_with_prometheus_and_follow_its_conventions(server, frame_json):
    httpx.post(f"{server.http_url}/v1/poses", json=frame_json, timeout=30).raise_for_status()
    page = httpx.get(f"{server.http_url}/metrics", timeout=10).text
    families = {f.name: f for f in text_string_to_metric_families(page)}
    posefuse = {n: f for n, f in families.items() if n.startswith("posefuse_")}
    assert not [n for n, f in posefuse.items() if not f.documentation], "every metric has HELP"
    # counters are present from zero (the parser names a counter family without `_total`)
    assert posefuse["posefuse_admission_refused"].type == "counter"
    latency = posefuse["posefuse_request_duration_seconds"]
    assert latency.type == "histogram"
    labels = [s.labels for s in latency.samples if s.name.endswith("_count")]
    assert {"transport": "http", "route": "/v1/poses", "status": "200"} in labels, labels
    info = [s for s in posefuse["posefuse_build_info"].samples if s.value == 1]
    assert len(info) == 1 and {"version", "bundle", "bundle_version"} <= info[0].labels.keys()
