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

fn describe() {
    use metrics::{describe_counter, describe_histogram, Unit};
    describe_counter!("posefuse_http_requests_total", "HTTP requests by route and status code");
    describe_counter!("posefuse_grpc_requests_total", "gRPC requests by method and status code");
    describe_counter!("posefuse_frames_total", "Frames predicted, by outcome (ok or error code)");
    describe_counter!("posefuse_persons_total", "Persons estimated, by the mode that ran");
    describe_histogram!("posefuse_queue_wait_seconds", Unit::Seconds, "Time jobs wait in the inference queue");
    describe_histogram!("posefuse_inference_seconds", Unit::Seconds, "ONNX Runtime time per batch, by model");
    describe_histogram!("posefuse_batch_size", Unit::Count, "Jobs per inference batch, by model");
    describe_histogram!("posefuse_preprocess_seconds", Unit::Seconds, "Pre- and post-processing time per frame");
    describe_histogram!("posefuse_decode_seconds", Unit::Seconds, "Image and point decoding time per frame");
    describe_histogram!("posefuse_request_seconds", Unit::Seconds, "Whole-frame prediction time");
}
