//! The runtime's queue: jobs queued together run as one batch, and batching does not change a
//! job's output.

mod server_support;

use std::sync::Arc;
use std::time::Duration;

use posefuse::runtime::{Bundle, Device, JobOutput, ModelKind, Runtime, RuntimeConfig};
use server_support::{input, model_dir, started_runtime};

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
