//! A request's spans in the runtime's queue: a job's `queue` span lasts until its network starts
//! on it. Alone in its binary, because it records spans with a subscriber of this thread's, which
//! other tests running beside it in one process could race (tracing caches per call site whether
//! anyone listens).

mod server_support;

use std::sync::Arc;
use std::time::Duration;

use posefuse::runtime::ModelKind;
use server_support::{input, started_runtime};

/// A span's name, its `model`, "open" or "close", and when.
type SpanEvent = (String, String, &'static str, std::time::Instant);

/// When each span opened and closed.
#[derive(Clone, Default)]
struct SpanTimes(Arc<std::sync::Mutex<Vec<SpanEvent>>>);

struct ModelField(String);

impl tracing::field::Visit for ModelField {
    fn record_str(&mut self, field: &tracing::field::Field, value: &str) {
        if field.name() == "model" {
            self.0 = value.to_string();
        }
    }
    fn record_debug(&mut self, field: &tracing::field::Field, value: &dyn std::fmt::Debug) {
        if field.name() == "model" {
            self.0 = format!("{value:?}").trim_matches('"').to_string();
        }
    }
}

impl<S> tracing_subscriber::Layer<S> for SpanTimes
where
    S: tracing::Subscriber + for<'a> tracing_subscriber::registry::LookupSpan<'a>,
{
    fn on_new_span(
        &self,
        attrs: &tracing::span::Attributes<'_>,
        id: &tracing::span::Id,
        ctx: tracing_subscriber::layer::Context<'_, S>,
    ) {
        let mut model = ModelField(String::new());
        attrs.record(&mut model);
        if let Some(span) = ctx.span(id) {
            self.0.lock().unwrap().push((span.name().to_string(), model.0.clone(), "open", std::time::Instant::now()));
            span.extensions_mut().insert(model);
        }
    }
    fn on_close(&self, id: tracing::span::Id, ctx: tracing_subscriber::layer::Context<'_, S>) {
        if let Some(span) = ctx.span(&id) {
            let model = span.extensions().get::<ModelField>().map(|m| m.0.clone()).unwrap_or_default();
            self.0.lock().unwrap().push((span.name().to_string(), model, "close", std::time::Instant::now()));
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_point_job_waits_in_its_queue_span_until_its_batch_starts() {
    use tracing_subscriber::layer::SubscriberExt;
    let rt = started_runtime().await;
    let (cam_len, fus_len, lid_len) = (
        rt.bundle().io(ModelKind::Camera).input_len(),
        rt.bundle().io(ModelKind::PointFusion).input_len(),
        rt.bundle().io(ModelKind::PointLidar).input_len(),
    );
    let times = SpanTimes::default();
    // The jobs are queued from this thread (the futures are polled here, not spawned), so their
    // queue spans are this subscriber's wherever the worker closes them.
    let _recording = tracing::subscriber::set_default(tracing_subscriber::registry().with(times.clone()));
    let pause = rt.pause();
    // a LiDAR-only person queued before a fusion person: one round, the camera batch first
    let lidar = rt.infer(ModelKind::PointLidar, input(lid_len, 1.0));
    let step = Box::new(move |_: &[f32]| vec![0.1; fus_len]);
    let chain = rt.infer_chain(input(cam_len, 2.0), ModelKind::PointFusion, step);
    let release = async {
        tokio::time::sleep(Duration::from_millis(100)).await;
        drop(pause);
    };
    let (lidar, chain, ()) = tokio::join!(lidar, chain, release);
    let (lidar, chain) = (lidar.unwrap(), chain.unwrap());
    assert!(lidar.queue > chain.queue, "the LiDAR job waited for the camera batch as well");
    let closed = |model: &str| {
        let got = times.0.lock().unwrap();
        got.iter()
            .find(|(n, m, e, _)| n == "queue" && m == model && *e == "close")
            .map(|t| t.3)
            .unwrap_or_else(|| panic!("no queue span of {model} closed: {got:?}"))
    };
    // The chain's wait ends when the round's camera batch starts; the LiDAR job's when its own
    // batch starts, after everything the chain ran in between (camera, step, point network:
    // `ModelKind::ALL` puts the fusion batch before the LiDAR one), timed in this same round.
    let (camera_started, lidar_started) = (closed("camera"), closed("point_lidar"));
    let between = lidar_started.saturating_duration_since(camera_started);
    let chain_ran = chain.inference + chain.between;
    assert!(
        between >= chain_ran,
        "the LiDAR job's queue span ended {between:?} after the chain's, which ran {chain_ran:?}"
    );
}
