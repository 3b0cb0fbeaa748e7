//! The camera + LiDAR pedestrian simulator (`posefuse simulate`).

pub mod body;
pub mod dataset;
pub mod hands;
pub mod labels;
pub mod lidar;
pub mod math;
pub mod poses;
pub mod preview;
pub mod raycast;
pub mod realism;
pub mod render;
pub mod scene;
pub mod stats;
pub mod street;
pub mod world;

use std::path::Path;

use crate::error::Context;
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;

use dataset::{simulate_frame, FrameResult, SampleStats};
use posefuse_core::pipeline::PipelineConfig;
use posefuse_core::sample::{Sample, ShardWriter};

/// Version of the simulator, written to `dataset.json`.
pub const SIM_VERSION: &str = "posefuse-sim-1";
/// Frames simulated per parallel batch.
const BATCH_FRAMES: usize = 48;
/// Samples shown on the preview contact sheets.
const PREVIEW_SAMPLES: usize = 24;

/// What `posefuse simulate` renders (the command line's flags, as plain values).
#[derive(Debug, Clone)]
pub struct SimulateOptions {
    /// Number of pedestrians (prepared samples) to generate.
    pub count: usize,
    /// Random seed; the same seed and arguments give byte-identical output.
    pub seed: u64,
    /// Output directory.
    pub out: std::path::PathBuf,
    /// Side S of the camera crops.
    pub image_size: u32,
    /// The point networks' frame the samples are prepared in.
    pub frame: posefuse_core::pipeline::PointFrame,
    /// Write PNG contact sheets to OUT/preview.
    pub preview: bool,
    /// Frames (from the first) that also get a request fixture in OUT/requests. Default: every
    /// frame when --count is at most 1000, otherwise the first 200.
    pub requests: Option<usize>,
    /// Most in-box points kept per sample in `points_xyz`/`points_uv` (P in docs/DATA.md).
    pub points_cap: usize,
    /// `clean` (tight clothing, empty hands, clean returns), `street` (loose clothing, things in
    /// hand, mixed-pixel LiDAR returns at silhouette edges) or `street-hard` (`street` and the
    /// effects that bring the LiDAR toward Waymo's; the CLI's default).
    pub profile: street::Profile,
    /// Realism effects added to the profile's own (docs/DATA.md, "Realism against Waymo's anchors").
    pub effects: Vec<realism::Effect>,
    /// Worker threads (default: all cores).
    pub jobs: Option<usize>,
}

/// The radius (model-input pixels) of the "LiDAR point near a keypoint" statistic: 2% of S.
pub fn near_px(cfg: &PipelineConfig) -> f64 {
    0.02 * cfg.image_size as f64
}

/// Runs `posefuse simulate`.
pub fn simulate(args: SimulateOptions) -> crate::error::Result<()> {
    let cfg = PipelineConfig::with_image_size(args.image_size).in_frame(args.frame);
    cfg.validate().map_err(|e| crate::invalid!("--image-size {}: {e}", args.image_size))?;
    crate::ensure!(args.count > 0, "--count must be positive");
    crate::ensure!(args.points_cap > 0, "--points-cap must be positive");
    let realism = realism::Realism::of(args.profile, &args.effects);
    let requests = args.requests.unwrap_or(if args.count <= 1000 { usize::MAX } else { 200 });
    let pool =
        rayon::ThreadPoolBuilder::new().num_threads(args.jobs.unwrap_or(0)).build().context("the worker threads")?;
    let out = &args.out;
    std::fs::create_dir_all(out.join("shards")).with_context(|| format!("creating {}", out.display()))?;
    if requests > 0 {
        std::fs::create_dir_all(out.join("requests"))?;
    }
    let started = std::time::Instant::now();
    let bar = ProgressBar::new(args.count as u64);
    bar.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:40}] {pos}/{len} samples ({per_sec}, eta {eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut shards = ShardWriter::new(&out.join("shards"), &cfg, args.points_cap);
    let mut stats: Vec<SampleStats> = Vec::with_capacity(args.count);
    let mut preview: Vec<Sample> = Vec::new();
    let (mut produced, mut next_frame, mut fixtures, mut frames) = (0usize, 0usize, 0usize, 0usize);
    let near = near_px(&cfg);
    let mut first_fixture: Option<String> = None;
    while produced < args.count {
        // About two samples per frame: small runs do not simulate a whole batch for nothing.
        let n_frames = (args.count - produced).div_ceil(2).clamp(2, BATCH_FRAMES);
        let batch: Vec<crate::error::Result<FrameResult>> = pool.install(|| {
            (next_frame..next_frame + n_frames)
                .into_par_iter()
                .map(|i| Ok(simulate_frame(args.seed, i, i < requests, &cfg, args.points_cap, near, realism)?))
                .collect()
        });
        next_frame += n_frames;
        for r in batch {
            let mut r = r?;
            let take = r.samples.len().min(args.count - produced);
            if take == 0 {
                continue;
            }
            frames += 1;
            r.samples.truncate(take);
            r.stats.truncate(take);
            if let Some(mut f) = r.fixture.take() {
                f.persons.truncate(take);
                let path = out.join("requests").join(format!("frame-{:06}.json", r.index));
                std::fs::write(&path, serde_json::to_vec(&f)?)
                    .with_context(|| format!("writing {}", path.display()))?;
                fixtures += 1;
                first_fixture.get_or_insert_with(|| format!("frame-{:06}.json", r.index));
            }
            stats.append(&mut r.stats);
            for s in r.samples {
                if args.preview && preview.len() < PREVIEW_SAMPLES {
                    preview.push(s.clone());
                }
                shards.push(s)?;
            }
            produced += take;
            bar.set_position(produced as u64);
        }
    }
    shards.flush()?;
    bar.finish_and_clear();
    let report = stats::report(&stats, near);
    write_dataset_json(out, &args, &cfg, requests.min(next_frame), frames, fixtures, &shards, &report)?;
    if args.preview {
        let dir = out.join("preview");
        std::fs::create_dir_all(&dir)?;
        let refs: Vec<&Sample> = preview.iter().collect();
        preview::sheet(&refs, cfg.image_size, 4).save(dir.join("sheet-000.png"))?;
        if let Some(name) = first_fixture {
            let frame: posefuse_core::frame::Frame =
                serde_json::from_slice(&std::fs::read(out.join("requests").join(&name))?)?;
            preview::frame_overview(&frame)?.save(dir.join(name.replace(".json", ".png")))?;
        }
    }
    let secs = started.elapsed().as_secs_f64();
    eprintln!(
        "simulated {} samples from {frames} frames ({fixtures} request fixtures) in {secs:.1} s ({:.0} samples/s) into {}",
        produced,
        produced as f64 / secs,
        out.display()
    );
    eprint!("{}", report.markdown());
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn write_dataset_json(
    out: &Path,
    args: &SimulateOptions,
    cfg: &PipelineConfig,
    request_frames: usize,
    frames: usize,
    fixtures: usize,
    shards: &ShardWriter,
    report: &stats::Report,
) -> crate::error::Result<()> {
    let doc = serde_json::json!({
        "version": SIM_VERSION,
        "profile": args.profile,
        "effects": realism::Realism::of(args.profile, &args.effects).effects(),
        "seed": args.seed,
        "count": args.count,
        "image_size": cfg.image_size,
        "points_cap": args.points_cap,
        "frames": frames,
        "request_frames": request_frames,
        "request_fixtures": fixtures,
        "shards": shards.written.iter().map(|(f, n)| serde_json::json!({"file": f, "samples": n})).collect::<Vec<_>>(),
        "lidar": {
            "origin": world::LIDAR_ORIGIN,
            "beams": lidar::BEAMS,
            "columns": lidar::COLUMNS,
            "range_noise_m": lidar::RANGE_NOISE_M,
            "max_range_m": lidar::MAX_RANGE,
            "inclinations_deg": lidar::inclinations().iter().map(|e| e.to_degrees()).collect::<Vec<_>>(),
        },
        "labels": {
            "noise_fraction_of_box_height": labels::LABEL_NOISE_FRACTION,
            "noise_cap_px": labels::LABEL_NOISE_CAP_PX,
            "box3d_margin_m": world::BOX3D_MARGIN,
        },
        "stats": report,
        "preprocessing": cfg,
    });
    let path = out.join("dataset.json");
    std::fs::write(&path, serde_json::to_vec_pretty(&doc)?).with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
