//! `posefuse mcap score`: a ROS 2 drive log in, its pedestrians' poses out as a new log
//! (docs/ROS.md). The input is streamed once (a reader thread decodes, groups and builds the
//! frames' requests, a few frames ahead of the answers); requests are answered concurrently by
//! the serving code (in this process or a running server) and written in time order.

use std::collections::{BTreeMap, HashMap};
use std::io::{BufReader, Read};
use std::path::PathBuf;
use std::time::Duration;

use futures::StreamExt;
use posefuse_data::error::Context;

use super::viz::{image_annotations, scene_update};
use crate::waymo_score::Scorer;
use posefuse_data::ros::build::{build_frame, raw_rgb, BuildOptions, Built};
use posefuse_data::ros::log_writer::LogWriter;
use posefuse_data::ros::msgs::{
    decode_tf, detection_layout_supported, schema, CameraInfo, CompressedImage, Detection3DArray, Image, PointCloud2,
};
use posefuse_data::ros::sync::{Assembled, Assembler, CameraImage, ImagePayload};
use posefuse_data::ros::tf::TfTree;
use posefuse_serve::service::limits::MAX_CAMERAS;

/// Output topics.
pub const SKELETONS_TOPIC: &str = "/posefuse/skeletons";
pub const POSES_TOPIC: &str = "/posefuse/poses";
pub const ANNOTATIONS_PREFIX: &str = "/posefuse/annotations";
/// The JSON channel's schema name.
pub const POSES_SCHEMA: &str = "posefuse.PoseResponse";

/// The largest record (a chunk or a message) read: a 64 MiB camera image or cloud is far past
/// any sensor's, and a malformed length cannot make the reader allocate more.
const MAX_RECORD_BYTES: usize = 256 << 20;
/// Distinct camera frames and transforms kept.
const MAX_CAMERA_INFOS: usize = 64;
const MAX_TF_FRAMES: usize = 4096;

/// What to score.
#[derive(Debug, Clone)]
pub struct McapScoreOptions {
    pub input: PathBuf,
    pub out: PathBuf,
    /// Image topics read (`CompressedImage` or `Image`); all of them when empty.
    pub image_topics: Vec<String>,
    /// `CameraInfo` topics read; all of them when empty. Paired with images by frame id.
    pub camera_info_topics: Vec<String>,
    /// The `PointCloud2` topic; the first one in the log when `None`.
    pub lidar_topic: Option<String>,
    /// The `Detection3DArray` topic; the first one in the log when `None`.
    pub boxes_topic: Option<String>,
    pub tf_topic: String,
    pub sync_ms: f64,
    pub pedestrian_classes: Vec<String>,
    /// Frames answered concurrently.
    pub concurrency: usize,
    pub timeout: Duration,
}

/// How often something was skipped, and the first time's details.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct Count {
    pub count: usize,
    pub first: String,
}

/// What a scoring run did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct McapScoreSummary {
    pub messages: u64,
    /// Box messages, each a frame.
    pub frames: usize,
    pub frames_answered: usize,
    pub persons: usize,
    /// Answered persons by the model path that ran.
    pub modes: BTreeMap<String, usize>,
    pub failed_requests: usize,
    /// Frames not answered, by reason.
    pub frames_skipped: BTreeMap<String, Count>,
    /// Cameras left out of answered frames, by reason.
    pub cameras_left_out: BTreeMap<String, Count>,
    /// Messages that could not be read, by topic.
    pub messages_skipped: BTreeMap<String, Count>,
    /// Topics read, by role.
    pub topics: BTreeMap<String, Vec<String>>,
    /// Topics in the log that were not read.
    pub topics_ignored: Vec<String>,
    /// Why the log could not be read to its end (what came before was scored and written).
    pub log_error: Option<String>,
    pub seconds: f64,
    pub frames_per_second: f64,
    pub out: String,
}

fn count(map: &mut BTreeMap<String, Count>, key: String, detail: impl FnOnce() -> String) {
    let c = map.entry(key).or_default();
    if c.count == 0 {
        c.first = detail();
    }
    c.count += 1;
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Role {
    Compressed,
    Raw,
    Info,
    Cloud,
    Tf,
    Boxes,
    Ignored,
}

/// Which role each channel plays (the flags, else the schema names).
struct Router<'a> {
    o: &'a McapScoreOptions,
    roles: HashMap<u16, Role>,
    lidar: Option<String>,
    boxes: Option<String>,
    images: Vec<String>,
    topics: BTreeMap<String, Vec<String>>,
    ignored: Vec<String>,
}

impl<'a> Router<'a> {
    fn new(o: &'a McapScoreOptions) -> Router<'a> {
        Router {
            o,
            roles: HashMap::new(),
            lidar: o.lidar_topic.clone(),
            boxes: o.boxes_topic.clone(),
            images: Vec::new(),
            topics: BTreeMap::new(),
            ignored: Vec::new(),
        }
    }

    fn role(&mut self, ch: &mcap::Channel) -> posefuse_data::error::Result<Role> {
        if let Some(r) = self.roles.get(&ch.id) {
            return Ok(*r);
        }
        let r = self.decide(ch)?;
        let label = match r {
            Role::Compressed | Role::Raw => "images",
            Role::Info => "camera_info",
            Role::Cloud => "lidar",
            Role::Tf => "tf_static",
            Role::Boxes => "boxes",
            Role::Ignored => "",
        };
        if r == Role::Ignored {
            self.ignored.push(ch.topic.clone());
        } else {
            self.topics.entry(label.into()).or_default().push(ch.topic.clone());
        }
        self.roles.insert(ch.id, r);
        Ok(r)
    }

    fn decide(&mut self, ch: &mcap::Channel) -> posefuse_data::error::Result<Role> {
        let topic = ch.topic.as_str();
        let schema_name = ch.schema.as_ref().map_or("", |s| s.name.as_str());
        let named = |list: &[String]| list.iter().any(|t| t == topic);
        let explicit = named(&self.o.image_topics)
            || named(&self.o.camera_info_topics)
            || self.o.lidar_topic.as_deref() == Some(topic)
            || self.o.boxes_topic.as_deref() == Some(topic);
        let role = match schema_name {
            schema::COMPRESSED_IMAGE | schema::IMAGE
                if self.o.image_topics.is_empty() && self.images.len() < MAX_CAMERAS || named(&self.o.image_topics) =>
            {
                if schema_name == schema::IMAGE {
                    Role::Raw
                } else {
                    Role::Compressed
                }
            }
            schema::CAMERA_INFO if self.o.camera_info_topics.is_empty() || named(&self.o.camera_info_topics) => {
                Role::Info
            }
            schema::POINT_CLOUD2 if self.lidar.as_deref().is_none_or(|t| t == topic) => Role::Cloud,
            schema::DETECTION3D_ARRAY if self.boxes.as_deref().is_none_or(|t| t == topic) => Role::Boxes,
            schema::TF_MESSAGE if topic == self.o.tf_topic => Role::Tf,
            _ if explicit => {
                posefuse_data::bail!("topic {topic}: schema `{schema_name}` is not the message type its flag reads")
            }
            _ => Role::Ignored,
        };
        if role == Role::Ignored {
            return Ok(role);
        }
        if ch.message_encoding != "cdr" {
            posefuse_data::ensure!(
                !explicit,
                "topic {topic}: message encoding `{}` is not ROS 2's cdr",
                ch.message_encoding
            );
            return Ok(Role::Ignored);
        }
        if role == Role::Boxes {
            let text = ch.schema.as_ref().map(|s| String::from_utf8_lossy(&s.data).into_owned()).unwrap_or_default();
            if !detection_layout_supported(&text) {
                posefuse_data::ensure!(!explicit, "topic {topic}: this vision_msgs Detection3D layout is not read (vision_msgs 4, ROS 2 Humble and later, is)");
                return Ok(Role::Ignored);
            }
        }
        match role {
            Role::Cloud => self.lidar = Some(topic.to_owned()),
            Role::Boxes => self.boxes = Some(topic.to_owned()),
            Role::Compressed | Role::Raw => self.images.push(topic.to_owned()),
            _ => {}
        }
        Ok(role)
    }
}

/// A frame ready to answer, or one that is not.
enum Job {
    Frame { stamp_ns: i64, base: String, built: Box<Built> },
    Skipped { stamp_ns: i64, base: String, reason: String },
}

/// Counts the bytes read, for the progress bar.
struct Progress<R> {
    inner: R,
    bar: indicatif::ProgressBar,
}

impl<R: Read> Read for Progress<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.bar.inc(n as u64);
        Ok(n)
    }
}

/// What the reader thread found besides frames.
#[derive(Default)]
struct ReadReport {
    messages: u64,
    messages_skipped: BTreeMap<String, Count>,
    topics: BTreeMap<String, Vec<String>>,
    ignored: Vec<String>,
    log_error: Option<String>,
}

/// The reader thread: the log in, jobs out (module docs).
fn read_log(
    o: &McapScoreOptions,
    bar: indicatif::ProgressBar,
    jobs: tokio::sync::mpsc::Sender<Job>,
) -> posefuse_data::error::Result<ReadReport> {
    let file = std::fs::File::open(&o.input).with_context(|| format!("opening {}", o.input.display()))?;
    let source = Progress { inner: BufReader::with_capacity(1 << 20, file), bar };
    let options = mcap::sans_io::LinearReaderOptions::default().with_record_length_limit(MAX_RECORD_BYTES);
    let reader = mcap::io::MessageReader::new_with_options(source, options);
    let mut router = Router::new(o);
    let mut report = ReadReport::default();
    let mut sync = Assembler::new(o.sync_ms);
    let mut tf = TfTree::default();
    let mut infos: BTreeMap<String, CameraInfo> = BTreeMap::new();
    let build = BuildOptions { pedestrian_classes: o.pedestrian_classes.clone() };
    let send = |a: Assembled, tf: &TfTree, infos: &BTreeMap<String, CameraInfo>| {
        let stamp_ns = a.boxes.header.stamp_ns;
        let base = a.boxes.header.frame_id.clone();
        let job = match build_frame(&a, tf, infos, &build) {
            Ok(built) => Job::Frame { stamp_ns, base, built: Box::new(built) },
            Err(skip) => Job::Skipped { stamp_ns, base, reason: skip.0 },
        };
        // a closed channel means the answering side has stopped: nothing waits for more
        jobs.blocking_send(job).is_ok()
    };
    for msg in reader {
        let msg = match msg {
            Ok(m) => m,
            Err(e) => {
                report.log_error = Some(format!(
                    "{}: the log cannot be read past message {}: {e}",
                    o.input.display(),
                    report.messages
                ));
                break;
            }
        };
        report.messages += 1;
        let role = router.role(&msg.channel)?;
        let topic = msg.channel.topic.as_str();
        let data = msg.data.as_ref();
        let decoded: Result<Vec<Assembled>, String> = (|| {
            Ok(match role {
                Role::Compressed => {
                    let m = CompressedImage::decode(data).map_err(|e| e.0)?;
                    let f = m.format.to_ascii_lowercase();
                    if !(f.contains("jpeg") || f.contains("jpg") || f.contains("png")) {
                        return Err(format!("CompressedImage format `{}` (jpeg and png are read)", m.format));
                    }
                    sync.push_image(CameraImage {
                        topic: topic.into(),
                        header: m.header,
                        payload: ImagePayload::Encoded(m.data),
                    });
                    vec![]
                }
                Role::Raw => {
                    let m = Image::decode(data).map_err(|e| e.0)?;
                    let payload = raw_rgb(&m.encoding, m.width, m.height, m.step, &m.data)?;
                    sync.push_image(CameraImage { topic: topic.into(), header: m.header, payload });
                    vec![]
                }
                Role::Info => {
                    let m = CameraInfo::decode(data).map_err(|e| e.0)?;
                    if infos.len() < MAX_CAMERA_INFOS || infos.contains_key(&m.header.frame_id) {
                        infos.insert(m.header.frame_id.clone(), m);
                    }
                    vec![]
                }
                Role::Cloud => {
                    sync.push_cloud(topic, PointCloud2::decode(data).map_err(|e| e.0)?);
                    vec![]
                }
                Role::Tf => {
                    let links = decode_tf(data).map_err(|e| e.0)?;
                    if tf.len() + links.len() <= MAX_TF_FRAMES {
                        tf.insert(&links);
                    }
                    vec![]
                }
                Role::Boxes => sync.push_boxes(Detection3DArray::decode(data).map_err(|e| e.0)?),
                Role::Ignored => vec![],
            })
        })();
        let mut ready = match decoded {
            Ok(r) => r,
            Err(e) => {
                let schema = msg.channel.schema.as_ref().map_or("", |s| s.name.as_str());
                count(&mut report.messages_skipped, format!("{topic}: {schema}"), || {
                    format!("message at log time {} ns: {e}", msg.log_time)
                });
                vec![]
            }
        };
        ready.extend(sync.ready(false));
        for a in ready {
            if !send(a, &tf, &infos) {
                return Ok(report);
            }
        }
    }
    for a in sync.ready(true) {
        if !send(a, &tf, &infos) {
            break;
        }
    }
    report.topics = router.topics;
    report.ignored = router.ignored;
    Ok(report)
}

/// The JSON Schema of the poses channel: the response's schema and those it refers to, from the
/// OpenAPI document, its references moved from `#/components/schemas` to `$defs`.
pub fn poses_json_schema() -> posefuse_data::error::Result<Vec<u8>> {
    const REF: &str = "#/components/schemas/";
    let doc = serde_json::to_value(posefuse_serve::server::http::openapi_doc())?;
    let all = doc.pointer("/components/schemas").and_then(|v| v.as_object()).cloned().unwrap_or_default();
    let mut defs = serde_json::Map::new();
    let mut todo = vec!["PoseResponse".to_owned()];
    while let Some(name) = todo.pop() {
        let Some(schema) = all.get(&name).filter(|_| !defs.contains_key(&name)) else { continue };
        let text = schema.to_string();
        todo.extend(text.split(REF).skip(1).filter_map(|rest| rest.split('"').next()).map(str::to_owned));
        defs.insert(name, schema.clone());
    }
    let text = serde_json::to_string(&serde_json::json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": POSES_SCHEMA,
        "$ref": "#/$defs/PoseResponse",
        "$defs": defs,
    }))?;
    Ok(text.replace(REF, "#/$defs/").into_bytes())
}

/// Runs `posefuse mcap score`.
pub async fn score(scorer: &Scorer<'_>, o: &McapScoreOptions) -> posefuse_data::error::Result<McapScoreSummary> {
    let started = std::time::Instant::now();
    posefuse_data::ensure!(o.sync_ms >= 0.0 && o.sync_ms.is_finite(), "--sync-ms must be a non-negative number");
    let size = std::fs::metadata(&o.input).with_context(|| format!("reading {}", o.input.display()))?.len();
    let bar = indicatif::ProgressBar::new(size).with_style(
        indicatif::ProgressStyle::with_template("{bar:40} {bytes}/{total_bytes} {msg} ({eta})")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let mut log = LogWriter::create(&o.out, "posefuse")?;
    let json_schema = poses_json_schema()?;
    let concurrency = o.concurrency.max(1);
    let (tx, mut rx) = tokio::sync::mpsc::channel::<Job>(2 * concurrency);
    let reader = {
        let (o, bar) = (o.clone(), bar.clone());
        std::thread::Builder::new().name("mcap-reader".into()).spawn(move || read_log(&o, bar, tx))?
    };
    let jobs = futures::stream::poll_fn(move |cx| rx.poll_recv(cx));
    let mut answers = jobs
        .map(|job| async move {
            match job {
                Job::Frame { stamp_ns, base, built } => {
                    let Built { frame, images, left_out } = *built;
                    let answer = scorer.answer(frame, o.timeout).await;
                    (stamp_ns, base, Ok((images, left_out, answer)))
                }
                Job::Skipped { stamp_ns, base, reason } => (stamp_ns, base, Err(reason)),
            }
        })
        .buffered(concurrency);
    let mut sum = McapScoreSummary::default();
    while let Some((stamp_ns, base, outcome)) = answers.next().await {
        sum.frames += 1;
        let mut persons = Vec::new();
        match outcome {
            Err(reason) => count(&mut sum.frames_skipped, reason.clone(), || format!("frame stamped {stamp_ns} ns")),
            Ok((images, left_out, answer)) => {
                for l in left_out {
                    let key = l.split_once(": ").map_or(l.clone(), |(cam, _)| cam.to_owned());
                    count(&mut sum.cameras_left_out, key, || l.clone());
                }
                match answer {
                    Ok(resp) => {
                        sum.frames_answered += 1;
                        sum.persons += resp.persons.len();
                        for p in &resp.persons {
                            *sum.modes.entry(p.mode.as_str().into()).or_default() += 1;
                        }
                        let id = log.channel(POSES_TOPIC, (POSES_SCHEMA, "jsonschema", &json_schema), "json")?;
                        log.write(id, stamp_ns, &serde_json::to_vec(&resp)?)?;
                        for img in &images {
                            let a = image_annotations(img.header.stamp_ns, &img.topic, &resp.persons);
                            log.foxglove(&format!("{ANNOTATIONS_PREFIX}{}", img.topic), stamp_ns, &a)?;
                        }
                        persons = resp.persons;
                    }
                    Err(e) => {
                        sum.failed_requests += 1;
                        count(&mut sum.frames_skipped, "the request failed".into(), || {
                            format!("frame stamped {stamp_ns} ns: {e:#}")
                        });
                    }
                }
            }
        }
        // every frame clears the last one's skeletons, answered or not
        log.foxglove(SKELETONS_TOPIC, stamp_ns, &scene_update(stamp_ns, &base, &persons))?;
        bar.set_message(format!("{} frames, {} persons", sum.frames, sum.persons));
    }
    let report = reader.join().map_err(|_| posefuse_data::invalid!("the log reader panicked"))??;
    bar.finish_and_clear();
    sum.messages = report.messages;
    sum.messages_skipped = report.messages_skipped;
    sum.topics = report.topics;
    sum.topics_ignored = report.ignored;
    sum.log_error = report.log_error;
    sum.out = log.finish()?.display().to_string();
    sum.seconds = started.elapsed().as_secs_f64();
    sum.frames_per_second = sum.frames as f64 / sum.seconds.max(1e-9);
    Ok(sum)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_poses_schema_is_self_contained() {
        let text = String::from_utf8(poses_json_schema().unwrap()).unwrap();
        assert!(!text.contains("#/components/"));
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert!(v.pointer("/$defs/PoseResponse/properties/persons").is_some());
        assert!(v.pointer("/$defs/PersonPose").is_some());
        // only what a response refers to
        assert!(v.pointer("/$defs/Frame").is_none());
    }
}
