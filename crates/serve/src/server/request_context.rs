//! Each request on the serving port, HTTP and gRPC alike: its id (`x-request-id`, taken from the
//! caller or made, and echoed), its W3C trace context (`traceparent`, continued or started, and
//! returned naming this server's span), a `request` span that every log line written while it is
//! answered carries, one access-log line and its latency metric. When the process exports spans
//! (OpenTelemetry, `--otlp-endpoint`), the `request` span is the caller's span's child and the
//! ids returned are the exported span's. See docs/OPERATIONS.md ("Following a request").

use std::time::Instant;

use axum::extract::Request;
use axum::http::{HeaderMap, HeaderValue, Response};
use axum::middleware::Next;
use opentelemetry::trace::{SpanContext, SpanId, TraceContextExt, TraceFlags, TraceId, TraceState};
use tracing::Instrument;
use tracing_opentelemetry::OpenTelemetrySpanExt;

/// The request-id header, accepted and echoed.
pub const REQUEST_ID: &str = "x-request-id";
/// The W3C Trace Context header.
pub const TRACEPARENT: &str = "traceparent";
/// A caller's request id longer than this (or empty, or not visible ASCII) is replaced.
pub const REQUEST_ID_MAX: usize = 128;

/// The route pattern a request was answered on, left on its response for the access log and the
/// latency metric (a bounded label, unlike the path).
#[derive(Debug, Clone)]
pub struct RouteLabel(pub String);

/// A request's place in a distributed trace.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TraceContext {
    pub trace_id: u128,
    /// The caller's span, when the caller sent a valid `traceparent`.
    pub parent_id: Option<u64>,
    /// This server's span for the request.
    pub span_id: u64,
    pub flags: u8,
}

impl TraceContext {
    /// Continues the caller's trace when its `traceparent` is valid, else starts `new_trace` (not
    /// sampled); either way this server's span is `span_id`. Zero ids are not ids (W3C): they
    /// are replaced by 1.
    pub fn from_headers(headers: &HeaderMap, span_id: u64, new_trace: u128) -> TraceContext {
        let given = headers.get(TRACEPARENT).and_then(|v| v.to_str().ok()).and_then(parse_traceparent);
        let span_id = span_id.max(1);
        match given {
            Some((trace_id, parent, flags)) => TraceContext { trace_id, parent_id: Some(parent), span_id, flags },
            None => TraceContext { trace_id: new_trace.max(1), parent_id: None, span_id, flags: 0 },
        }
    }

    /// The `traceparent` naming this server's span, for the response and for calls it makes.
    pub fn traceparent(&self) -> String {
        format!("00-{:032x}-{:016x}-{:02x}", self.trace_id, self.span_id, self.flags)
    }

    pub fn trace_id_hex(&self) -> String {
        format!("{:032x}", self.trace_id)
    }

    /// The caller's span as OpenTelemetry's remote parent, when the caller sent one.
    fn remote_parent(&self) -> Option<opentelemetry::Context> {
        let parent = self.parent_id?;
        let sc = SpanContext::new(
            TraceId::from_bytes(self.trace_id.to_be_bytes()),
            SpanId::from_bytes(parent.to_be_bytes()),
            TraceFlags::new(self.flags),
            true,
            TraceState::default(),
        );
        Some(opentelemetry::Context::new().with_remote_span_context(sc))
    }

    /// Links `span` to the caller's span and, when spans are exported (the span has an
    /// OpenTelemetry context of its own), takes that span's trace id, id and sampling flag, so
    /// that what is returned and logged names what the collector receives.
    fn adopt(self, span: &tracing::Span) -> TraceContext {
        if let Some(cx) = self.remote_parent() {
            let _ = span.set_parent(cx);
        }
        let otel = span.context().span().span_context().clone();
        if !otel.is_valid() {
            return self;
        }
        TraceContext {
            trace_id: u128::from_be_bytes(otel.trace_id().to_bytes()),
            parent_id: self.parent_id,
            span_id: u64::from_be_bytes(otel.span_id().to_bytes()),
            flags: otel.trace_flags().to_u8(),
        }
    }
}

/// `version-trace_id-parent_id-flags` (W3C Trace Context level 1): lowercase hex of 2, 32, 16 and
/// 2 digits; version `ff` and all-zero ids are invalid; version 00 has exactly these four fields,
/// a later version may append more (read as version 00).
fn parse_traceparent(s: &str) -> Option<(u128, u64, u8)> {
    let mut fields = s.split('-');
    let (version, trace, parent, flags) = (fields.next()?, fields.next()?, fields.next()?, fields.next()?);
    let hex = |f: &str, n: usize| f.len() == n && f.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b));
    if !(hex(version, 2) && hex(trace, 32) && hex(parent, 16) && hex(flags, 2)) || version == "ff" {
        return None;
    }
    if version == "00" && fields.next().is_some() {
        return None;
    }
    let (trace_id, parent_id) = (u128::from_str_radix(trace, 16).ok()?, u64::from_str_radix(parent, 16).ok()?);
    if trace_id == 0 || parent_id == 0 {
        return None;
    }
    Some((trace_id, parent_id, u8::from_str_radix(flags, 16).ok()?))
}

/// The caller's `x-request-id` when usable (1 to [`REQUEST_ID_MAX`] visible ASCII characters),
/// else `made()`.
pub fn request_id(headers: &HeaderMap, made: impl FnOnce() -> String) -> String {
    headers
        .get(REQUEST_ID)
        .and_then(|v| v.to_str().ok())
        .filter(|s| !s.is_empty() && s.len() <= REQUEST_ID_MAX && s.bytes().all(|b| b.is_ascii_graphic()))
        .map_or_else(made, str::to_string)
}

/// The canonical name of a gRPC status code (as grpc-go and OpenTelemetry write it).
pub fn grpc_code_name(code: tonic::Code) -> &'static str {
    use tonic::Code::*;
    match code {
        Ok => "OK",
        Cancelled => "CANCELLED",
        Unknown => "UNKNOWN",
        InvalidArgument => "INVALID_ARGUMENT",
        DeadlineExceeded => "DEADLINE_EXCEEDED",
        NotFound => "NOT_FOUND",
        AlreadyExists => "ALREADY_EXISTS",
        PermissionDenied => "PERMISSION_DENIED",
        ResourceExhausted => "RESOURCE_EXHAUSTED",
        FailedPrecondition => "FAILED_PRECONDITION",
        Aborted => "ABORTED",
        OutOfRange => "OUT_OF_RANGE",
        Unimplemented => "UNIMPLEMENTED",
        Internal => "INTERNAL",
        Unavailable => "UNAVAILABLE",
        DataLoss => "DATA_LOSS",
        Unauthenticated => "UNAUTHENTICATED",
    }
}

/// What the access log and the latency metric say of a response: the route label and status.
/// gRPC: the status of the response's headers (an error answered at once); one sent only in the
/// trailers, after a stream's messages, reads OK here (it is counted per method by
/// `posefuse_grpc_requests_total`).
fn outcome<B>(resp: &Response<B>, grpc: bool, path: &str) -> (String, String) {
    let route = resp.extensions().get::<RouteLabel>().map(|r| r.0.clone());
    if !grpc {
        return (route.unwrap_or_else(|| "unmatched".into()), resp.status().as_str().to_string());
    }
    let code = resp
        .headers()
        .get("grpc-status")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<i32>().ok())
        .map_or(tonic::Code::Ok, tonic::Code::from_i32);
    // Unknown methods answer UNIMPLEMENTED: their paths are the caller's, not a bounded label.
    let route =
        route.unwrap_or_else(|| if code == tonic::Code::Unimplemented { "unmatched".into() } else { path.into() });
    (route, grpc_code_name(code).to_string())
}

/// Middleware of the serving port (outermost but for the in-flight count).
pub async fn trace_request(req: Request, next: Next) -> axum::response::Response {
    let t0 = Instant::now();
    let given = TraceContext::from_headers(req.headers(), rand::random(), rand::random());
    let grpc = super::is_grpc(&req);
    let (method, path) = (req.method().clone(), req.uri().path().to_string());
    let span = tracing::info_span!("request", request_id = tracing::field::Empty, trace_id = tracing::field::Empty);
    let trace = given.adopt(&span);
    let id = request_id(req.headers(), || trace.trace_id_hex());
    span.record("request_id", id.as_str());
    span.record("trace_id", trace.trace_id_hex().as_str());
    let mut unanswered = Unanswered(Some(Access { t0, grpc, method, path, span: span.clone() }));
    let mut resp = next.run(req).instrument(span).await;
    let Some(access) = unanswered.0.take() else { return resp };
    let (route, status) = outcome(&resp, grpc, &access.path);
    if let Ok(v) = HeaderValue::from_str(&id) {
        resp.headers_mut().insert(REQUEST_ID, v);
    }
    if let Ok(v) = HeaderValue::from_str(&trace.traceparent()) {
        resp.headers_mut().insert(TRACEPARENT, v);
    }
    access.record(route, status);
    resp
}

/// What one access-log line and its latency sample need to know of a request.
struct Access {
    t0: Instant,
    grpc: bool,
    method: axum::http::Method,
    path: String,
    span: tracing::Span,
}

impl Access {
    fn record(self, route: String, status: String) {
        let secs = self.t0.elapsed().as_secs_f64();
        let transport = if self.grpc { "grpc" } else { "http" };
        metrics::histogram!("posefuse_request_duration_seconds", "transport" => transport, "route" => route, "status" => status.clone())
            .record(secs);
        self.span.in_scope(|| {
            tracing::info!(
                target: "posefuse::access",
                transport,
                method = %self.method,
                path = self.path,
                status,
                duration_ms = secs * 1e3,
                "answered"
            )
        });
    }
}

/// A request whose client went away before its answer (the connection closed, the HTTP/2
/// stream reset): hyper drops its future, and with it this guard, which writes its access line
/// as nginx does, 499 (`CANCELLED` for gRPC), so that it is neither missing from the log nor
/// counted as a server error. Its route is a frame route's label, or `unmatched`: the router
/// that would have named it never answered.
struct Unanswered(Option<Access>);

impl Drop for Unanswered {
    fn drop(&mut self) {
        let Some(access) = self.0.take() else { return };
        let route = super::early_admission::frame_route(&access.method, &access.path, access.grpc)
            .map_or_else(|| "unmatched".to_string(), |r| r.label(&access.path));
        let status = if access.grpc { grpc_code_name(tonic::Code::Cancelled).to_string() } else { "499".to_string() };
        access.record(route, status);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn headers(pairs: &[(&'static str, &str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.insert(*k, HeaderValue::from_str(v).unwrap());
        }
        h
    }

    const GIVEN: &str = "00-4bf92f3577b34da6a3ce929d0e0e4736-00f067aa0ba902b7-01";

    #[test]
    fn a_valid_traceparent_is_continued_under_this_servers_span() {
        let t = TraceContext::from_headers(&headers(&[(TRACEPARENT, GIVEN)]), 0x1234, 99);
        assert_eq!(t.trace_id, 0x4bf92f3577b34da6a3ce929d0e0e4736);
        assert_eq!((t.parent_id, t.span_id, t.flags), (Some(0x00f067aa0ba902b7), 0x1234, 1));
        assert_eq!(t.traceparent(), "00-4bf92f3577b34da6a3ce929d0e0e4736-0000000000001234-01");
        // a later version may carry more fields
        let later = "01-4bf92f3577b34da6a3ce929d0e0e4736-00f067aa0ba902b7-00-extra";
        let t = TraceContext::from_headers(&headers(&[(TRACEPARENT, later)]), 7, 99);
        assert_eq!((t.trace_id, t.flags), (0x4bf92f3577b34da6a3ce929d0e0e4736, 0));
    }

    #[test]
    fn an_invalid_traceparent_starts_a_new_unsampled_trace() {
        let bad = [
            "",
            "00-4bf92f3577b34da6a3ce929d0e0e4736-00f067aa0ba902b7",
            "00-4BF92F3577B34DA6A3CE929D0E0E4736-00f067aa0ba902b7-01",
            "00-00000000000000000000000000000000-00f067aa0ba902b7-01",
            "00-4bf92f3577b34da6a3ce929d0e0e4736-0000000000000000-01",
            "ff-4bf92f3577b34da6a3ce929d0e0e4736-00f067aa0ba902b7-01",
            "00-4bf92f3577b34da6a3ce929d0e0e473-00f067aa0ba902b7-01",
            "00-4bf92f3577b34da6a3ce929d0e0e4736-00f067aa0ba902b7-01-extra",
            "00-4bf92f3577b34da6a3ce929d0e0e4736-00f067aa0ba902bz-01",
        ];
        for b in bad {
            let t = TraceContext::from_headers(&headers(&[(TRACEPARENT, b)]), 5, 42);
            assert_eq!((t.trace_id, t.parent_id, t.span_id, t.flags), (42, None, 5, 0), "{b:?}");
        }
        let none = TraceContext::from_headers(&HeaderMap::new(), 0, 0);
        assert_eq!((none.trace_id, none.span_id), (1, 1), "zero ids are replaced");
    }

    #[test]
    fn a_usable_request_id_is_kept_and_others_are_made() {
        let made = || "made".to_string();
        assert_eq!(request_id(&headers(&[(REQUEST_ID, "abc-123_X")]), made), "abc-123_X");
        assert_eq!(request_id(&headers(&[(REQUEST_ID, &"a".repeat(REQUEST_ID_MAX))]), made).len(), REQUEST_ID_MAX);
        for bad in ["", "has space", &"a".repeat(REQUEST_ID_MAX + 1)] {
            assert_eq!(request_id(&headers(&[(REQUEST_ID, bad)]), made), "made", "{bad:?}");
        }
        assert_eq!(request_id(&HeaderMap::new(), made), "made");
    }

    #[test]
    fn grpc_codes_have_their_canonical_names() {
        let names: Vec<&str> = (0..17).map(|c| grpc_code_name(tonic::Code::from_i32(c))).collect();
        assert_eq!(names[0], "OK");
        assert_eq!(names[3], "INVALID_ARGUMENT");
        assert_eq!(names[8], "RESOURCE_EXHAUSTED");
        assert_eq!(names[16], "UNAUTHENTICATED");
        assert!(names.iter().all(|n| n.bytes().all(|b| b.is_ascii_uppercase() || b == b'_')));
        let distinct: std::collections::BTreeSet<&str> = names.iter().copied().collect();
        assert_eq!(distinct.len(), 17);
    }

    #[test]
    fn the_outcome_of_grpc_reads_the_header_status_and_bounds_the_route() {
        let ok = Response::new(());
        assert_eq!(outcome(&ok, true, "/p.S/M"), ("/p.S/M".to_string(), "OK".to_string()));
        let mut unknown = Response::new(());
        unknown.headers_mut().insert("grpc-status", HeaderValue::from_static("12"));
        assert_eq!(outcome(&unknown, true, "/any/thing"), ("unmatched".to_string(), "UNIMPLEMENTED".to_string()));
        let mut http = Response::new(());
        *http.status_mut() = axum::http::StatusCode::TOO_MANY_REQUESTS;
        http.extensions_mut().insert(RouteLabel("/v1/poses".into()));
        assert_eq!(outcome(&http, false, "/v1/poses"), ("/v1/poses".to_string(), "429".to_string()));
        assert_eq!(outcome(&Response::new(()), false, "/x").0, "unmatched");
    }
}
