//! Prometheus exposition. The `metrics` facade has one global recorder per process, so it is
//! installed once and shared by every server in the process.

use std::sync::OnceLock;

use metrics_exporter_prometheus::{Matcher, PrometheusBuilder, PrometheusHandle};

static HANDLE: OnceLock<Option<PrometheusHandle>> = OnceLock::new();

/// Latency buckets (seconds): 100 µs … 10 s.
const SECONDS: [f64; 14] =
    [0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 1.0, 2.5, 10.0];
const BATCH: [f64; 8] = [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0];

/// Installs the Prometheus recorder (first call) and returns its handle; `None` when another
/// recorder was installed first.
pub fn install() -> Option<PrometheusHandle> {
    HANDLE
        .get_or_init(|| {
            let builder = PrometheusBuilder::new()
                .set_buckets_for_metric(Matcher::Suffix("_seconds".into()), &SECONDS)
                .and_then(|b| b.set_buckets_for_metric(Matcher::Full("posefuse_batch_size".into()), &BATCH));
            let recorder = match builder {
                Ok(b) => b.build_recorder(),
                Err(e) => {
                    tracing::warn!("prometheus buckets: {e}");
                    return None;
                }
            };
            let handle = recorder.handle();
            match metrics::set_global_recorder(recorder) {
                Ok(()) => {
                    describe();
                    Some(handle)
                }
                Err(_) => {
                    tracing::warn!("a metrics recorder is already installed; /metrics will be empty");
                    None
                }
            }
        })
        .clone()
}

/// HELP and unit for every metric the server writes (one place, so none is left without), and
/// the counters and per-model histograms present from zero: a rate over a counter that appears
/// only at its first event misses that event.
fn describe() {
    use metrics::{describe_counter, describe_gauge, describe_histogram, Unit};
    describe_counter!("posefuse_http_requests_total", "HTTP requests by route and status code");
    describe_counter!("posefuse_grpc_requests_total", "gRPC requests by method and canonical status code");
    describe_counter!("posefuse_frames_total", "Frames predicted, by outcome (ok or error code)");
    describe_counter!("posefuse_persons_total", "Persons estimated, by the mode that ran");
    describe_counter!("posefuse_persons_skipped_total", "Persons of answered frames left out, each with its error");
    describe_counter!("posefuse_frames_abandoned_total", "Frames whose work stopped because nobody waited any more");
    describe_counter!("posefuse_admission_refused_total", "Frames refused at admission (the server was full)");
    describe_counter!("posefuse_accept_errors_total", "Failed accepts on the listener (e.g. out of file descriptors)");
    describe_counter!(
        "posefuse_connections_refused_total",
        "Connections closed at once: the connection cap was reached"
    );
    describe_counter!("posefuse_connections_evicted_total", "Idle connections closed to make room for new ones");
    describe_counter!("posefuse_connections_idle_closed_total", "Connections closed after the idle timeout");
    describe_counter!(
        "posefuse_memory_trims_total",
        "Times the server, quiet after work, returned its heaps' free pages to the OS"
    );
    describe_gauge!("posefuse_connections_open", "Connections open on the serving port");
    describe_gauge!("posefuse_requests_in_flight", "Requests being answered on the serving port");
    describe_gauge!("posefuse_frames_admitted", "Frames admitted and not yet answered");
    describe_gauge!("posefuse_preprocess_in_flight", "Frames being decoded and pre-processed");
    describe_gauge!("posefuse_admission_waiting", "Admitted frames waiting for a pre-processing permit");
    describe_gauge!("posefuse_admission_line", "Frames waiting for admission, their bodies not yet read");
    describe_gauge!("posefuse_queue_depth", "Jobs in the inference queue");
    describe_gauge!("posefuse_build_info", "1 for the running build and serving bundle (labels), 0 once replaced");
    describe_histogram!(
        "posefuse_request_duration_seconds",
        Unit::Seconds,
        "Time from a request's arrival to its response headers, by transport, route and status"
    );
    describe_histogram!(
        "posefuse_queue_wait_seconds",
        Unit::Seconds,
        "Time jobs wait in the inference queue, by model"
    );
    describe_histogram!("posefuse_inference_seconds", Unit::Seconds, "ONNX Runtime time per batch, by model");
    describe_histogram!("posefuse_batch_size", Unit::Count, "Jobs per inference batch, by model");
    describe_histogram!("posefuse_preprocess_seconds", Unit::Seconds, "Pre- and post-processing time per frame");
    describe_histogram!("posefuse_decode_seconds", Unit::Seconds, "Image and point decoding time per frame");
    describe_histogram!("posefuse_request_seconds", Unit::Seconds, "Whole-frame prediction time");
    for name in [
        "posefuse_persons_skipped_total",
        "posefuse_frames_abandoned_total",
        "posefuse_admission_refused_total",
        "posefuse_accept_errors_total",
        "posefuse_connections_refused_total",
        "posefuse_connections_evicted_total",
        "posefuse_connections_idle_closed_total",
        "posefuse_memory_trims_total",
    ] {
        metrics::counter!(name).increment(0);
    }
    metrics::counter!("posefuse_frames_total", "outcome" => "ok").increment(0);
    // read beside `posefuse_admission_refused_total`, so present before anyone waits
    metrics::gauge!("posefuse_admission_line").set(0.0);
    for kind in crate::runtime::ModelKind::ALL {
        let _ = metrics::histogram!("posefuse_queue_wait_seconds", "model" => kind.key());
    }
}

/// `posefuse_build_info`: 1 for this build with the bundle `name` at `version`, or 0 for a
/// bundle that was replaced.
pub fn build_info(bundle: &str, bundle_version: &str, serving: bool) {
    metrics::gauge!(
        "posefuse_build_info",
        "version" => env!("CARGO_PKG_VERSION"),
        "bundle" => bundle.to_string(),
        "bundle_version" => bundle_version.to_string()
    )
    .set(if serving { 1.0 } else { 0.0 });
}

/// Counts a gRPC call under its method and canonical status name.
pub fn count_grpc(method: &'static str, code: tonic::Code) {
    metrics::counter!("posefuse_grpc_requests_total", "method" => method, "code" => super::request_context::grpc_code_name(code))
        .increment(1);
}
