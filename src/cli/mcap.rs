//! `posefuse mcap ...`: ROS 2 drive logs (docs/ROS.md).

use std::path::PathBuf;

use posefuse::ros::record::{record, RecordOptions};
use posefuse::ros::score::{score, McapScoreOptions};

/// Arguments of `posefuse mcap`.
#[derive(Debug, clap::Args)]
pub struct McapArgs {
    #[command(subcommand)]
    pub command: McapCommand,
}

#[derive(Debug, clap::Subcommand)]
pub enum McapCommand {
    /// Predict every pedestrian of every frame of a ROS 2 log; write the poses as a new log
    /// (Foxglove scene updates and image annotations, and the full responses as JSON).
    Score(Box<McapScoreArgs>),
    /// Write a Waymo v2 dataset root (e.g. from `posefuse waymo simulate`) as a ROS 2 log.
    Record(McapRecordArgs),
}

/// Arguments of `posefuse mcap score`.
#[derive(Debug, clap::Args)]
pub struct McapScoreArgs {
    /// The drive log (MCAP, ROS 2 CDR messages).
    #[arg(long = "in")]
    pub input: PathBuf,
    /// The log of poses to write (replaced when complete).
    #[arg(long)]
    pub out: PathBuf,
    /// A camera's image topic (sensor_msgs/msg/CompressedImage or Image); repeat for each camera.
    /// Default: every image topic of the log (at most 8).
    #[arg(long = "image-topic")]
    pub image_topics: Vec<String>,
    /// A sensor_msgs/msg/CameraInfo topic; repeat for each camera. Default: all of them. Infos
    /// pair with images by their header's frame_id.
    #[arg(long = "camera-info-topic")]
    pub camera_info_topics: Vec<String>,
    /// The sensor_msgs/msg/PointCloud2 topic. Default: the log's first.
    #[arg(long)]
    pub lidar_topic: Option<String>,
    /// The vision_msgs/msg/Detection3DArray topic of the detector's 3D boxes. Default: the log's
    /// first.
    #[arg(long)]
    pub boxes_topic: Option<String>,
    /// The static transforms' topic (tf2_msgs/msg/TFMessage).
    #[arg(long, default_value = "/tf_static")]
    pub tf_topic: String,
    /// A box message takes the cloud and images stamped at most this far from it.
    #[arg(long, default_value_t = 50.0)]
    pub sync_ms: f64,
    /// Detection classes that are pedestrians (class_id of any hypothesis, any case).
    #[arg(long = "pedestrian-class", value_delimiter = ',', default_value = "pedestrian,person,2")]
    pub pedestrian_classes: Vec<String>,
    #[command(flatten)]
    pub scoring: super::commands::ScoringArgs,
}

/// Arguments of `posefuse mcap record`.
#[derive(Debug, clap::Args)]
pub struct McapRecordArgs {
    /// Dataset root: ROOT/<component>/<segment>.parquet.
    #[arg(long)]
    pub dataset: PathBuf,
    /// The log to write.
    #[arg(long)]
    pub out: PathBuf,
    /// At most this many frames (segments in name order).
    #[arg(long)]
    pub frames: Option<usize>,
}

/// `posefuse mcap ...`.
pub fn run(a: McapArgs) -> anyhow::Result<()> {
    super::commands::init_tracing(false);
    match a.command {
        McapCommand::Record(r) => {
            let sum = record(&RecordOptions { dataset: r.dataset, out: r.out, max_frames: r.frames })?;
            println!("{}", serde_json::to_string_pretty(&sum)?);
            Ok(())
        }
        McapCommand::Score(a) => {
            let a = *a;
            let o = McapScoreOptions {
                input: a.input,
                out: a.out,
                image_topics: a.image_topics,
                camera_info_topics: a.camera_info_topics,
                lidar_topic: a.lidar_topic,
                boxes_topic: a.boxes_topic,
                tf_topic: a.tf_topic,
                sync_ms: a.sync_ms,
                pedestrian_classes: a.pedestrian_classes,
                concurrency: a.scoring.concurrency,
                timeout: super::commands::CLI_FRAME_TIMEOUT,
            };
            let answerer = a.scoring.answerer()?;
            let sum = super::commands::tokio_runtime()?.block_on(score(&answerer.scorer(), &o))?;
            println!("{}", serde_json::to_string_pretty(&sum)?);
            match sum.log_error {
                Some(e) => anyhow::bail!("{e}"),
                None => Ok(()),
            }
        }
    }
}
