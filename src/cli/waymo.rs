//! `posefuse waymo ...`: the Waymo Open Dataset v2 commands (docs/WAYMO.md).

use std::path::PathBuf;

use posefuse::pipeline::PointFrame;
use posefuse::sim::street::Profile;
use posefuse::waymo::convert::{convert, ConvertOptions};
use posefuse::waymo::schema::{name_value, CAMERA_NAMES};
use posefuse::waymo::score::score;
use posefuse::waymo::sim::WaymoSimOptions;

/// Arguments of `posefuse waymo`.
#[derive(Debug, clap::Args)]
pub struct WaymoArgs {
    #[command(subcommand)]
    pub command: WaymoCommand,
}

#[derive(Debug, clap::Subcommand)]
pub enum WaymoCommand {
    /// Write simulated segments in the v2 layout (ROOT/<component>/<segment>.parquet).
    Simulate(WaymoSimulateArgs),
    /// Convert a v2 dataset root to training shards and request fixtures (as `posefuse simulate`
    /// writes them).
    Convert(WaymoConvertArgs),
    /// Predict every pedestrian of every frame; predictions as parquet in lidar_hkp's layout.
    Score(WaymoScoreArgs),
    /// Waymo's keypoint metrics of predictions against the dataset's lidar_hkp.
    Eval(WaymoEvalArgs),
}

/// Arguments of `posefuse waymo score`.
#[derive(Debug, clap::Args)]
pub struct WaymoScoreArgs {
    /// Dataset root: ROOT/<component>/<segment>.parquet.
    #[arg(long)]
    pub dataset: PathBuf,
    /// Predictions directory: one <segment>.parquet per segment (existing ones are skipped).
    #[arg(long)]
    pub out: PathBuf,
    /// `i/k`: score the segments whose index in name order is i modulo k (k machines split a
    /// dataset; a Kubernetes Indexed Job passes its index as i).
    #[arg(long, default_value = "0/1", value_parser = parse_shard)]
    pub shard: (usize, usize),
    #[command(flatten)]
    pub scoring: super::commands::ScoringArgs,
}

/// Arguments of `posefuse waymo eval`.
#[derive(Debug, clap::Args)]
pub struct WaymoEvalArgs {
    /// Dataset root with lidar_hkp (the ground truth) and lidar_box.
    #[arg(long)]
    pub dataset: PathBuf,
    /// Predictions directory written by `posefuse waymo score`.
    #[arg(long)]
    pub predictions: PathBuf,
    /// Print a machine-readable JSON report instead of a table.
    #[arg(long)]
    pub json: bool,
}

fn parse_shard(s: &str) -> Result<(usize, usize), String> {
    let (i, k) = s.split_once('/').ok_or_else(|| format!("{s:?} is not i/k"))?;
    let i: usize = i.trim().parse().map_err(|e| format!("{s:?}: {e}"))?;
    let k: usize = k.trim().parse().map_err(|e| format!("{s:?}: {e}"))?;
    if k == 0 || i >= k {
        return Err(format!("{s:?}: needs 0 <= i < k"));
    }
    Ok((i, k))
}

/// Arguments of `posefuse waymo simulate`.
#[derive(Debug, clap::Args)]
pub struct WaymoSimulateArgs {
    /// Dataset root to write.
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[arg(long, default_value_t = 1)]
    pub segments: usize,
    /// Frames per segment (10 Hz).
    #[arg(long, default_value_t = 20)]
    pub frames: usize,
    /// TOP range image rows.
    #[arg(long, default_value_t = 64)]
    pub top_rows: usize,
    /// TOP range image columns.
    #[arg(long, default_value_t = 2650)]
    pub top_cols: usize,
    /// Rows of the four short-range lasers' range images.
    #[arg(long, default_value_t = 200)]
    pub short_rows: usize,
    /// Columns of the four short-range lasers' range images.
    #[arg(long, default_value_t = 600)]
    pub short_cols: usize,
    /// Camera images are 1920×1280 times this.
    #[arg(long, default_value_t = 1.0)]
    pub image_scale: f64,
    /// Vehicle speed, m/s (straight ahead).
    #[arg(long, default_value_t = 15.0)]
    pub speed: f64,
    /// Fraction of camera objects with keypoint labels.
    #[arg(long, default_value_t = 0.35)]
    pub keypoint_fraction: f64,
    /// Store columns in the physical types other releases use (names as strings, int32 lists,
    /// float for double and double for float).
    #[arg(long)]
    pub alt_types: bool,
    /// The pedestrians' realism profile, as `posefuse simulate --profile`.
    #[arg(long, value_enum, default_value_t = Profile::StreetHard)]
    pub profile: Profile,
    /// Frames per row group of every component.
    #[arg(long, default_value_t = 4)]
    pub frames_per_row_group: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub jobs: Option<usize>,
}

/// Arguments of `posefuse waymo convert`.
#[derive(Debug, clap::Args)]
pub struct WaymoConvertArgs {
    /// Dataset root: ROOT/<component>/<segment>.parquet (e.g. the release's `training/`).
    #[arg(long)]
    pub dataset: PathBuf,
    /// Output directory (shards/, requests/, dataset.json).
    #[arg(long)]
    pub out: PathBuf,
    /// At most this many segments (in name order).
    #[arg(long)]
    pub segments: Option<usize>,
    /// Only these cameras (FRONT, FRONT_LEFT, FRONT_RIGHT, SIDE_LEFT, SIDE_RIGHT or 1..5),
    /// comma separated.
    #[arg(long, value_delimiter = ',')]
    pub cameras: Option<Vec<String>>,
    /// Side S of the camera crops.
    #[arg(long, default_value_t = 256)]
    pub image_size: u32,
    /// The point networks' frame the samples are prepared in (docs/BUNDLE.md, "Point frame").
    #[arg(long, value_enum, default_value_t = PointFrame::BoxHeading)]
    pub frame: PointFrame,
    /// Most in-box points kept per sample (P in docs/DATA.md).
    #[arg(long, default_value_t = 1024)]
    pub points_cap: usize,
    /// Do not write request fixtures.
    #[arg(long)]
    pub no_requests: bool,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub jobs: Option<usize>,
}

/// `posefuse waymo ...`.
pub fn run(a: WaymoArgs) -> anyhow::Result<()> {
    match a.command {
        WaymoCommand::Simulate(s) => Ok(posefuse::waymo::sim::run(&WaymoSimOptions {
            out: s.out,
            seed: s.seed,
            segments: s.segments,
            frames: s.frames,
            top: [s.top_rows, s.top_cols],
            short: [s.short_rows, s.short_cols],
            image_scale: s.image_scale,
            speed_mps: s.speed,
            keypoint_fraction: s.keypoint_fraction,
            alt_types: s.alt_types,
            profile: s.profile,
            frames_per_row_group: s.frames_per_row_group,
            jobs: s.jobs,
        })?),
        WaymoCommand::Convert(c) => {
            let cameras = c
                .cameras
                .map(|v| {
                    v.iter()
                        .map(|s| {
                            name_value(&CAMERA_NAMES, s)
                                .ok_or_else(|| anyhow::anyhow!("--cameras: unknown camera {s:?}"))
                        })
                        .collect::<anyhow::Result<Vec<i64>>>()
                })
                .transpose()?;
            let sum = convert(&ConvertOptions {
                dataset: c.dataset,
                out: c.out.clone(),
                segments: c.segments,
                cameras,
                image_size: c.image_size,
                frame: c.frame,
                points_cap: c.points_cap,
                requests: !c.no_requests,
                jobs: c.jobs,
            })?;
            eprintln!(
                "converted {} segment(s), {} frames into {} samples and {} request fixtures in {:.1} s ({:.1} frames/s) into {}",
                sum.segments,
                sum.frames,
                sum.samples,
                sum.fixtures,
                sum.seconds,
                sum.frames as f64 / sum.seconds.max(1e-9),
                c.out.display()
            );
            Ok(())
        }
        WaymoCommand::Score(a) => {
            super::commands::init_tracing(false);
            let o = posefuse::waymo::score::ScoreOptions {
                dataset: a.dataset,
                out: a.out,
                shard: a.shard,
                concurrency: a.scoring.concurrency,
                timeout: super::commands::CLI_FRAME_TIMEOUT,
            };
            let answerer = a.scoring.answerer()?;
            let sum = super::commands::tokio_runtime()?.block_on(score(&answerer.scorer(), &o))?;
            eprintln!(
                "scored {} segment(s) ({} already done), {} frames, {} persons, {} failed requests in {:.1} s ({:.1} frames/s)",
                sum.segments_scored,
                sum.segments_skipped,
                sum.frames,
                sum.persons,
                sum.failed_requests,
                sum.seconds,
                sum.frames as f64 / sum.seconds.max(1e-9)
            );
            Ok(())
        }
        WaymoCommand::Eval(a) => {
            let r = posefuse::waymo::score::evaluate(&a.dataset, &a.predictions)?;
            if a.json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                println!("{} segment(s), {} labelled pedestrians without a prediction", r.segments, r.missing);
                print!("{}", r.metrics.table());
            }
            Ok(())
        }
    }
}
