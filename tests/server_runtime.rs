//! The runtime's queue: jobs queued together run as one batch, and batching does not change a
//! job's output.

mod server_support;

use std::sync::Arc;
use std::time::Duration;

use posefuse::runtime::{Bundle, Device, JobOutput, ModelKind, Runtime, RuntimeConfig};
use server_support::model_dir;

fn input(len: usize, seed: f32) -> Vec<f32> {
    (0..len).map(|i| ((i as f32 * 0.37 + seed).sin()) * 0.5).collect()
}

/// A warmed-up runtime on the test bundle that batches up to 8 jobs.
async fn started_runtime() -> Arc<Runtime> {
    let bundle = Arc::new(Bundle::load(&model_dir()).unwrap());
    let cfg = RuntimeConfig { max_batch: 8, ..RuntimeConfig::default() };
    let rt = Arc::new(tokio::task::spawn_blocking(move || Runtime::start(bundle, &cfg)).await.unwrap().unwrap());
    assert!(rt.wait_ready(Duration::from_secs(60)));
    rt
}

/// `n` jobs submitted while the workers are paused (so they queue together), then their outputs.
async fn queued_while_paused<F, Fut>(rt: &Arc<Runtime>, n: usize, job: F) -> Vec<JobOutput>
where
    F: Fn(Arc<Runtime>, usize) -> Fut,
    Fut: std::future::Future<Output = posefuse::error::Result<JobOutput>> + Send + 'static,
{
    let pause = rt.pause();
    let jobs: Vec<_> = (0..n).map(|i| tokio::spawn(job(rt.clone(), i))).collect();
    tokio::time::sleep(Duration::from_millis(200)).await;
    drop(pause);
    let mut outs = Vec::new();
    for j in jobs {
        outs.push(j.await.unwrap().unwrap());
    }
    outs
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn queued_jobs_form_one_batch_with_unchanged_outputs() {
    let rt = started_runtime().await;
    let len = rt.bundle().io(ModelKind::PointLidar).input_len();

    // Alone: a batch of one.
    let alone = rt.infer(ModelKind::PointLidar, input(len, 1.0)).await.unwrap();
    assert_eq!(alone.batch, 1);
    assert_eq!(alone.data.len(), rt.bundle().io(ModelKind::PointLidar).output_len());

    // Five jobs queued while the worker is paused run together.
    let outs = queued_while_paused(&rt, 5, |rt, i| async move {
        rt.infer(ModelKind::PointLidar, input(len, 1.0 + i as f32)).await
    })
    .await;
    // The worker may have taken the first job before pausing; the rest share a batch.
    assert!(outs[1..].iter().all(|o| o.batch >= 4), "{:?}", outs.iter().map(|o| o.batch).collect::<Vec<_>>());
    let max_diff = outs[0].data.iter().zip(&alone.data).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    assert!(max_diff < 1e-4, "batched output differs by {max_diff}");
    assert!(outs.iter().all(|o| o.queue >= Duration::from_millis(100)));

    // Wrong input sizes are refused before queueing.
    let e = rt.infer(ModelKind::Camera, vec![0.0; 3]).await.unwrap_err();
    assert!(e.to_string().contains("camera"), "{e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_chain_equals_its_two_jobs_and_batches_with_others() {
    let rt = started_runtime().await;
    let (cam_len, pt_len) =
        (rt.bundle().io(ModelKind::Camera).input_len(), rt.bundle().io(ModelKind::PointFusion).input_len());
    // a step that depends on the heatmaps, so a wrong hand-over shows in the point output
    let step = move |h: &[f32]| -> Vec<f32> { (0..pt_len).map(|i| h[i % h.len()] * 2.0 - 0.5).collect() };

    let heatmaps = rt.infer(ModelKind::Camera, input(cam_len, 2.0)).await.unwrap().data;
    let points = rt.infer(ModelKind::PointFusion, step(&heatmaps)).await.unwrap().data;
    let chained = rt.infer_chain(input(cam_len, 2.0), ModelKind::PointFusion, Box::new(step)).await.unwrap();
    assert_eq!(chained.camera.as_deref(), Some(heatmaps.as_slice()));
    assert_eq!(chained.data, points);

    // Chains queued together share the camera batch and the point batch.
    let outs = queued_while_paused(&rt, 3, |rt, i| async move {
        rt.infer_chain(input(cam_len, 3.0 + i as f32), ModelKind::PointFusion, Box::new(step)).await
    })
    .await;
    assert!(outs[1..].iter().all(|o| o.batch >= 2), "{:?}", outs.iter().map(|o| o.batch).collect::<Vec<_>>());
    assert!(outs.iter().all(|o| o.camera.as_ref().is_some_and(|h| h.len() == heatmaps.len())));

    // A chain must end in a point network, and a step of the wrong size is an error, not a panic.
    let e = rt.infer_chain(input(cam_len, 1.0), ModelKind::Camera, Box::new(step)).await.unwrap_err();
    assert!(e.to_string().contains("point network"), "{e}");
    let e = rt.infer_chain(input(cam_len, 1.0), ModelKind::PointFusion, Box::new(|_: &[f32]| vec![0.0; 5])).await;
    assert!(e.unwrap_err().to_string().contains("expected"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_whose_callers_gave_up_are_not_computed() {
    let rt = started_runtime().await;
    let len = rt.bundle().io(ModelKind::PointLidar).input_len();
    let pause = rt.pause();
    let live = tokio::spawn({
        let rt = rt.clone();
        async move { rt.infer(ModelKind::PointLidar, input(len, 1.0)).await }
    });
    tokio::time::sleep(Duration::from_millis(50)).await;
    let abandoned: Vec<_> = (0..5)
        .map(|i| {
            let rt = rt.clone();
            tokio::spawn(async move { rt.infer(ModelKind::PointLidar, input(len, 2.0 + i as f32)).await })
        })
        .collect();
    tokio::time::sleep(Duration::from_millis(100)).await;
    // A deadline or a hang-up drops the caller's future, and with it the reply channel.
    for job in &abandoned {
        job.abort();
    }
    tokio::time::sleep(Duration::from_millis(50)).await;
    drop(pause);
    let out = live.await.unwrap().unwrap();
    assert_eq!(out.batch, 1, "the five abandoned jobs were run beside the live one");
}

#[test]
fn cuda_from_the_cpu_build_refuses_to_start_and_says_how_to_get_it() {
    // The set-up's default ONNX Runtime is the CPU build (scripts/setup.sh without --gpu).
    let bundle = Arc::new(Bundle::load(&model_dir()).unwrap());
    let cfg = RuntimeConfig { device: Device::Cuda(0), ..RuntimeConfig::default() };
    let e = Runtime::start(bundle.clone(), &cfg).err().expect("CUDA from the CPU build").to_string();
    assert!(e.contains("--device cuda:0") && e.contains("no CUDA execution provider"), "{e}");
    assert!(e.contains("scripts/setup.sh --gpu"), "{e}");
    let cpu = RuntimeConfig { device: Device::Cpu, ..RuntimeConfig::default() };
    assert!(Runtime::start(bundle, &cpu).is_ok());
}

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
    let camera_alone = rt.infer(ModelKind::Camera, input(cam_len, 2.0)).await.unwrap().inference;
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
    // the chain's wait ends when the round's camera batch starts, the LiDAR job's when its own
    // batch starts, after the camera network (half its time alone: room for a faster run)
    let (camera_started, lidar_started) = (closed("camera"), closed("point_lidar"));
    assert!(
        lidar_started.saturating_duration_since(camera_started) >= camera_alone / 2,
        "the LiDAR job's queue span ended {:?} after the chain's; the camera network takes {camera_alone:?}",
        lidar_started.saturating_duration_since(camera_started)
    );
}
