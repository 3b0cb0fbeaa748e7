//! `posefuse waymo score` and `posefuse waymo eval`: every pedestrian of every frame through
//! the serving path (in-process [`Predictor`]), predictions written per segment as parquet in
//! `lidar_hkp`'s own column layout; and Waymo's keypoint metrics of such predictions against a
//! dataset's `lidar_hkp`.
//!
//! Predictions come from the in-process predictor or from a running server (`--server`).
//! Each pedestrian is predicted once per frame: with the camera whose associated box is the
//! largest (all of a frame's cameras in one request, each person naming its camera), or from the
//! LiDAR alone when no camera box is associated with it.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Duration;

use futures::StreamExt;
use posefuse_data::error::Context;

use posefuse_core::frame::{Box3d, Frame, FrameCamera, Person, Points, RequestedMode};
use posefuse_core::geometry::Camera;
use posefuse_core::keypoints::K;
use posefuse_core::metrics::{box_scale_3d, evaluate_person_partial, MetricsAccumulator, MetricsReport};
use posefuse_data::waymo::convert::{frame_points, kp3d_of, near_boxes, Kp3dLabel};
use posefuse_data::waymo::reader::{FrameData, FrameLabels, Segment};
use posefuse_data::waymo::schema::{comp, key};
use posefuse_data::waymo::segments::write_lidar_keypoints;
use posefuse_data::waymo::table::{read_columns, Columns, ComponentWriter};
use posefuse_serve::service::api::PoseResponse;
use posefuse_serve::service::Predictor;

/// Where predictions come from.
pub enum Scorer<'a> {
    /// The serving code path in this process.
    InProcess(&'a Predictor),
    /// A running server's `POST /v1/poses` (`host:port`).
    Server(String),
}

impl Scorer<'_> {
    pub async fn answer(&self, frame: Frame, timeout: Duration) -> posefuse_data::error::Result<PoseResponse> {
        match self {
            Scorer::InProcess(p) => Ok(p.answer(frame, None, timeout).await?),
            Scorer::Server(addr) => tokio::time::timeout(timeout, post_poses(addr, &frame))
                .await
                .map_err(|_| posefuse_data::invalid!("{addr}: timed out"))?,
        }
    }
}

/// `host:port` of a server URL (`http://host:port/` or `host:port`).
pub fn server_addr(url: &str) -> posefuse_data::error::Result<String> {
    let rest = url.strip_prefix("http://").unwrap_or(url);
    posefuse_data::ensure!(!url.starts_with("https://"), "--server {url}: only plain http is supported");
    let addr = rest.trim_end_matches('/');
    posefuse_data::ensure!(!addr.is_empty() && !addr.contains('/'), "--server {url}: expected http://host:port");
    Ok(if addr.contains(':') { addr.to_owned() } else { format!("{addr}:80") })
}

/// One `POST /v1/poses` over HTTP/1.1 (one connection per request).
async fn post_poses(addr: &str, frame: &Frame) -> posefuse_data::error::Result<PoseResponse> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let body = serde_json::to_vec(frame)?;
    let mut s = tokio::net::TcpStream::connect(addr).await.with_context(|| format!("connecting to {addr}"))?;
    let head = format!(
        "POST /v1/poses HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    s.write_all(head.as_bytes()).await?;
    s.write_all(&body).await?;
    let mut buf = Vec::new();
    s.read_to_end(&mut buf).await?;
    let split = buf
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .ok_or_else(|| posefuse_data::invalid!("{addr}: malformed response"))?;
    let head = String::from_utf8_lossy(&buf[..split]).to_ascii_lowercase();
    let mut body = buf[split + 4..].to_vec();
    if head.contains("transfer-encoding: chunked") {
        body = dechunk(&body)?;
    }
    let status: u16 = head.split_whitespace().nth(1).and_then(|c| c.parse().ok()).unwrap_or(0);
    posefuse_data::ensure!(status == 200, "{addr}: HTTP {status}: {}", String::from_utf8_lossy(&body));
    Ok(serde_json::from_slice(&body)?)
}

fn dechunk(mut b: &[u8]) -> posefuse_data::error::Result<Vec<u8>> {
    let mut out = Vec::new();
    loop {
        let eol = b.windows(2).position(|w| w == b"\r\n").ok_or_else(|| posefuse_data::invalid!("bad chunked body"))?;
        let size_text = String::from_utf8_lossy(&b[..eol]);
        let size =
            usize::from_str_radix(size_text.split(';').next().unwrap_or("").trim(), 16).context("a chunk size")?;
        b = &b[eol + 2..];
        if size == 0 {
            return Ok(out);
        }
        posefuse_data::ensure!(b.len() >= size + 2, "truncated chunked body");
        out.extend_from_slice(&b[..size]);
        b = &b[size + 2..];
    }
}

/// What to score.
#[derive(Debug, Clone)]
pub struct ScoreOptions {
    pub dataset: PathBuf,
    pub out: PathBuf,
    /// `(i, k)`: the segments whose index (in name order) is `i` mod `k`.
    pub shard: (usize, usize),
    /// Frames predicted concurrently.
    pub concurrency: usize,
    pub timeout: Duration,
}

/// The requests of one frame: each pedestrian once (module docs).
pub fn scoring_requests(
    seg: &Segment,
    cameras: &std::collections::BTreeMap<i64, Camera>,
    f: &FrameData,
    labels: &FrameLabels,
) -> posefuse_data::error::Result<Vec<Frame>> {
    let points = frame_points(&seg.lasers, f, true)?;
    let mut by_camera: std::collections::BTreeMap<i64, Vec<Person>> = Default::default();
    let mut lidar_only = Vec::new();
    for p in &labels.pedestrians {
        let best = labels
            .camera_objects
            .iter()
            .filter(|c| c.laser_object.as_deref() == Some(p.id.as_str()) && cameras.contains_key(&c.camera))
            .filter(|c| f.images.contains_key(&c.camera))
            .max_by(|a, b| (a.box2d.width * a.box2d.height).total_cmp(&(b.box2d.width * b.box2d.height)));
        let person = Person {
            id: p.id.clone(),
            camera: None,
            box_2d: best.map(|c| c.box2d),
            box_3d: p.box3d,
            ground_truth: None,
        };
        match best {
            Some(c) => by_camera.entry(c.camera).or_default().push(person),
            None => lidar_only.push(person),
        }
    }
    let mut out = Vec::new();
    let boxes = |ps: &[Person]| ps.iter().map(|p| p.box_3d).collect::<Vec<Box3d>>();
    // the cameras that show a pedestrian go in one request, each person naming its camera
    let mut seen = Vec::new();
    let mut frame_cameras = Vec::with_capacity(by_camera.len());
    for (cam, persons) in by_camera {
        use base64::Engine;
        let name = camera_name(cam);
        frame_cameras.push(FrameCamera {
            name: name.clone(),
            image: f.images.get(&cam).map(|j| base64::engine::general_purpose::STANDARD.encode(j)),
            image_rgb: None,
            calibration: cameras[&cam].to_calibration(),
        });
        seen.extend(persons.into_iter().map(|p| Person { camera: Some(name.clone()), ..p }));
    }
    if !seen.is_empty() {
        out.push(Frame {
            frame_id: Some(format!("{}/{}/cameras", seg.name, f.timestamp)),
            image: None,
            image_rgb: None,
            calibration: None,
            cameras: frame_cameras,
            points: Points::encode(&near_boxes(&points, &boxes(&seen))),
            persons: seen,
            mode: RequestedMode::Auto,
        });
    }
    if !lidar_only.is_empty() {
        let calibration = match cameras.values().next() {
            Some(c) => c.to_calibration(),
            None => posefuse_core::geometry::nominal_camera()?.to_calibration(),
        };
        out.push(Frame {
            frame_id: Some(format!("{}/{}/lidar", seg.name, f.timestamp)),
            image: None,
            image_rgb: None,
            calibration: Some(calibration),
            cameras: Vec::new(),
            points: Points::encode(&near_boxes(&points, &boxes(&lidar_only))),
            persons: lidar_only,
            mode: RequestedMode::Auto,
        });
    }
    Ok(out)
}

/// A camera's name in requests: Waymo's (`FRONT`, ...), else its number.
fn camera_name(cam: i64) -> String {
    let known = usize::try_from(cam - 1).ok().and_then(|i| posefuse_data::waymo::schema::CAMERA_NAMES.get(i));
    known.map_or_else(|| cam.to_string(), |n| n.to_string())
}

/// What a scoring run did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct ScoreSummary {
    pub segments_scored: usize,
    pub segments_skipped: usize,
    pub frames: usize,
    pub persons: usize,
    pub failed_requests: usize,
    pub seconds: f64,
}

/// The segments of shard `i` of `k`.
pub fn shard_segments(all: Vec<String>, (i, k): (usize, usize)) -> Vec<String> {
    all.into_iter().enumerate().filter(|(n, _)| k == 0 || n % k == i).map(|(_, s)| s).collect()
}

/// Runs `posefuse waymo score`. A segment whose predictions file
/// exists is skipped (rerun to resume); files appear only when complete.
pub async fn score(scorer: &Scorer<'_>, o: &ScoreOptions) -> posefuse_data::error::Result<ScoreSummary> {
    let started = std::time::Instant::now();
    posefuse_data::ensure!(o.shard.1 > 0 && o.shard.0 < o.shard.1, "--shard i/k needs 0 ≤ i < k");
    let names = shard_segments(posefuse_data::waymo::segments::segments_in(&o.dataset)?, o.shard);
    std::fs::create_dir_all(&o.out).with_context(|| format!("creating {}", o.out.display()))?;
    let mut sum = ScoreSummary::default();
    let bar = indicatif::ProgressBar::new(names.len() as u64);
    for name in &names {
        let dest = o.out.join(format!("{name}.parquet"));
        if dest.is_file() {
            sum.segments_skipped += 1;
            bar.inc(1);
            continue;
        }
        let mut seg = Segment::open(&o.dataset, name, &None)?;
        let cameras: std::collections::BTreeMap<i64, Camera> = seg
            .cameras
            .iter()
            .map(|(n, c)| Camera::from_calibration(c).map(|cam| (*n, cam)))
            .collect::<posefuse_core::Result<_>>()
            .map_err(|e| posefuse_data::invalid!("segment {name}: component `camera_calibration`: {e}"))?;
        let mut rows: Vec<(i64, String, Vec<Kp3dLabel>)> = Vec::new();
        for ts in seg.timestamps.clone() {
            let labels = seg.labels(ts);
            if labels.pedestrians.is_empty() {
                continue;
            }
            let wanted: Vec<i64> = cameras.keys().copied().collect();
            let f = seg.frame(ts, &wanted)?;
            let requests = scoring_requests(&seg, &cameras, &f, &labels)?;
            let answers: Vec<_> = futures::stream::iter(requests)
                .map(|r| scorer.answer(r, o.timeout))
                .buffer_unordered(o.concurrency.max(1))
                .collect()
                .await;
            for a in answers {
                match a {
                    Ok(resp) => {
                        for p in resp.persons {
                            let kps = p
                                .keypoints
                                .iter()
                                .map(|k| Kp3dLabel { kind: k.waymo_type as i64, xyz: k.xyz, occluded: false })
                                .collect();
                            rows.push((ts, p.id, kps));
                            sum.persons += 1;
                        }
                    }
                    Err(e) => {
                        sum.failed_requests += 1;
                        tracing::warn!(segment = %name, ts, error = %e, "request failed");
                    }
                }
            }
            sum.frames += 1;
        }
        write_predictions(&o.out, name, &rows)?;
        sum.segments_scored += 1;
        bar.inc(1);
    }
    bar.finish_and_clear();
    sum.seconds = started.elapsed().as_secs_f64();
    Ok(sum)
}

/// Writes `OUT/<segment>.parquet` (through a temporary name, renamed when complete).
pub fn write_predictions(
    out: &Path,
    segment: &str,
    rows: &[(i64, String, Vec<Kp3dLabel>)],
) -> posefuse_data::error::Result<()> {
    let tmp_name = format!(".{segment}.partial");
    let mut c = Columns::new(false);
    c.string(key::SEGMENT, &vec![segment.to_owned(); rows.len()]);
    c.int64(key::TIMESTAMP, &rows.iter().map(|r| r.0).collect::<Vec<_>>());
    c.string(key::LASER_OBJECT, &rows.iter().map(|r| r.1.clone()).collect::<Vec<_>>());
    write_lidar_keypoints(&mut c, &rows.iter().map(|r| r.2.as_slice()).collect::<Vec<_>>());
    let tmp_dir = out.join(&tmp_name);
    let mut w = ComponentWriter::new(&tmp_dir, ".", segment)?;
    w.write(&c.finish()?)?;
    w.finish()?;
    let written = posefuse_data::waymo::table::component_path(&tmp_dir, ".", segment);
    std::fs::rename(&written, out.join(format!("{segment}.parquet")))?;
    let _ = std::fs::remove_dir_all(&tmp_dir);
    Ok(())
}

/// Keypoints by (timestamp, laser object id) of a file in `lidar_hkp`'s layout.
fn read_keypoints(
    path: &Path,
    component: &str,
) -> posefuse_data::error::Result<HashMap<(i64, String), Vec<Kp3dLabel>>> {
    use posefuse_data::waymo::schema::col;
    let t = read_columns(
        path,
        component,
        &[key::TIMESTAMP, key::LASER_OBJECT, col::LHKP_TYPE, col::LHKP_X, col::LHKP_Y, col::LHKP_Z],
        None,
    )?;
    let (ts, ids, kinds) = (t.i64s(key::TIMESTAMP)?, t.strings(key::LASER_OBJECT)?, t.i64_lists(col::LHKP_TYPE)?);
    let (x, y, z) = (t.f64_lists(col::LHKP_X)?, t.f64_lists(col::LHKP_Y)?, t.f64_lists(col::LHKP_Z)?);
    let mut out = HashMap::new();
    for i in 0..t.rows() {
        let n = kinds[i].len().min(x[i].len()).min(y[i].len()).min(z[i].len());
        let kps = (0..n)
            .map(|k| Kp3dLabel { kind: kinds[i][k], xyz: [x[i][k], y[i][k], z[i][k]], occluded: false })
            .collect();
        out.insert((ts[i], ids[i].clone()), kps);
    }
    Ok(out)
}

/// Waymo's keypoint metrics of a predictions directory against a dataset's `lidar_hkp`.
#[derive(Debug, Clone, serde::Serialize)]
pub struct WaymoEvalReport {
    pub segments: usize,
    /// Labelled pedestrians with no prediction (scored as missing: OKS 0, PEM 0.25 m).
    pub missing: usize,
    pub metrics: MetricsReport,
}

/// Runs `posefuse waymo eval`.
pub fn evaluate(dataset: &Path, predictions: &Path) -> posefuse_data::error::Result<WaymoEvalReport> {
    let names = posefuse_data::waymo::segments::segments_in(dataset)?;
    let mut acc = MetricsAccumulator::new();
    let (mut segments, mut missing) = (0, 0);
    for name in &names {
        let gt_path = posefuse_data::waymo::table::component_path(dataset, comp::LIDAR_HKP, name);
        let pred_path = predictions.join(format!("{name}.parquet"));
        if !gt_path.is_file() || !pred_path.is_file() {
            continue;
        }
        segments += 1;
        let gt = read_keypoints(&gt_path, comp::LIDAR_HKP)?;
        let pred = read_keypoints(&pred_path, "predictions")?;
        let seg = Segment::open(dataset, name, &Some(vec![]))?;
        for ((ts, id), kps) in &gt {
            let Some(b) = seg.labels(*ts).pedestrians.into_iter().find(|p| &p.id == id) else {
                continue;
            };
            let g = kp3d_of(kps);
            // Waymo's mask: every labelled keypoint, occluded or not
            let labelled: Vec<bool> = g.iter().map(Option::is_some).collect();
            if !labelled.iter().any(|v| *v) {
                continue;
            }
            let gt_xyz: Vec<[f64; 3]> = g.iter().map(|x| x.map_or([0.0; 3], |x| x.at)).collect();
            let p: Vec<Option<[f64; 3]>> = match pred.get(&(*ts, id.clone())) {
                Some(pk) => kp3d_of(pk).iter().map(|x| x.map(|x| x.at)).collect(),
                None => {
                    missing += 1;
                    vec![None; K]
                }
            };
            let e = evaluate_person_partial(&p, &gt_xyz, &labelled, box_scale_3d(&b.box3d))?;
            acc.add_eval_3d(&e);
        }
    }
    posefuse_data::ensure!(
        segments > 0,
        "no segment has both {}/lidar_hkp and a predictions file in {}",
        dataset.display(),
        predictions.display()
    );
    Ok(WaymoEvalReport { segments, missing, metrics: acc.report() })
}
