//! Frames out of a stream of sensor messages: each box message (the detector's output for one
//! LiDAR sweep) takes the cloud and, per camera, the image whose header stamps are nearest its
//! own within the sync window. Logs are written in arrival order, not stamp order (a detector's
//! boxes arrive a few hundred milliseconds after the sweep they were made from), so messages are
//! kept for [`REORDER_MS`] past the window, and a box message is answered once a message stamped
//! that much later has arrived: the log is read once, holding a few messages per topic.

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;

use super::msgs::{Detection3DArray, Header, PointCloud2};

/// How much later than its stamp a message may arrive in the log and still be matched.
pub const REORDER_MS: f64 = 500.0;

/// Messages kept per topic, whatever their stamps: bounds memory on a log whose stamps stall.
pub const MAX_BUFFERED: usize = 32;

/// A camera image as it came.
#[derive(Debug, Clone, PartialEq)]
pub enum ImagePayload {
    /// `CompressedImage` bytes (JPEG or PNG).
    Encoded(Vec<u8>),
    /// `Image`, converted to packed RGB.
    Rgb { width: u32, height: u32, pixels: Vec<u8> },
}

/// One camera image.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraImage {
    pub topic: String,
    pub header: Header,
    pub payload: ImagePayload,
}

/// The messages of one frame.
#[derive(Debug, Clone)]
pub struct Assembled {
    pub boxes: Detection3DArray,
    /// The cloud and its topic.
    pub cloud: Option<(String, Arc<PointCloud2>)>,
    pub images: Vec<Arc<CameraImage>>,
}

trait Stamped {
    fn stamp(&self) -> i64;
}

impl Stamped for PointCloud2 {
    fn stamp(&self) -> i64 {
        self.header.stamp_ns
    }
}

impl Stamped for CameraImage {
    fn stamp(&self) -> i64 {
        self.header.stamp_ns
    }
}

/// Groups messages into frames (module docs).
#[derive(Debug)]
pub struct Assembler {
    sync_ns: i64,
    /// The window plus [`REORDER_MS`].
    hold_ns: i64,
    latest_ns: i64,
    clouds: VecDeque<Arc<PointCloud2>>,
    cloud_topic: String,
    images: BTreeMap<String, VecDeque<Arc<CameraImage>>>,
    pending: VecDeque<Detection3DArray>,
}

fn nearest<T: Stamped>(q: &VecDeque<Arc<T>>, at: i64, within: i64) -> Option<Arc<T>> {
    q.iter().filter(|m| (m.stamp() - at).abs() <= within).min_by_key(|m| (m.stamp() - at).abs()).cloned()
}

fn bounded_push<T>(q: &mut VecDeque<T>, v: T) {
    if q.len() == MAX_BUFFERED {
        q.pop_front();
    }
    q.push_back(v);
}

impl Assembler {
    pub fn new(sync_ms: f64) -> Assembler {
        let sync_ns = (sync_ms * 1e6).round() as i64;
        Assembler {
            sync_ns,
            hold_ns: sync_ns + (REORDER_MS * 1e6) as i64,
            latest_ns: i64::MIN,
            clouds: VecDeque::new(),
            cloud_topic: String::new(),
            images: BTreeMap::new(),
            pending: VecDeque::new(),
        }
    }

    fn saw(&mut self, stamp: i64) {
        self.latest_ns = self.latest_ns.max(stamp);
    }

    /// Clouds of one topic (the router reads one).
    pub fn push_cloud(&mut self, topic: &str, c: PointCloud2) {
        self.saw(c.header.stamp_ns);
        if self.cloud_topic != topic {
            self.cloud_topic = topic.to_owned();
        }
        bounded_push(&mut self.clouds, Arc::new(c));
    }

    pub fn push_image(&mut self, i: CameraImage) {
        self.saw(i.header.stamp_ns);
        bounded_push(self.images.entry(i.topic.clone()).or_default(), Arc::new(i));
    }

    /// Box messages past [`MAX_BUFFERED`] answer the oldest at once with what is there.
    pub fn push_boxes(&mut self, b: Detection3DArray) -> Vec<Assembled> {
        self.saw(b.header.stamp_ns);
        self.pending.push_back(b);
        let mut out = Vec::new();
        if self.pending.len() > MAX_BUFFERED {
            out.extend(self.pending.pop_front().map(|b| self.assemble(b)));
        }
        out
    }

    /// Frames whose window has passed; all of them when the log has ended.
    pub fn ready(&mut self, log_ended: bool) -> Vec<Assembled> {
        let mut out = Vec::new();
        while let Some(b) = self.pending.front() {
            if !log_ended && b.header.stamp_ns.saturating_add(self.hold_ns) >= self.latest_ns {
                break;
            }
            if let Some(b) = self.pending.pop_front() {
                out.push(self.assemble(b));
            }
        }
        self.prune();
        out
    }

    fn assemble(&self, boxes: Detection3DArray) -> Assembled {
        let at = boxes.header.stamp_ns;
        let images = self.images.values().filter_map(|q| nearest(q, at, self.sync_ns)).collect();
        let cloud = nearest(&self.clouds, at, self.sync_ns).map(|c| (self.cloud_topic.clone(), c));
        Assembled { cloud, images, boxes }
    }

    /// Drops what no waiting box message can take, nor one still to arrive (stamped at most
    /// [`REORDER_MS`] before the latest message).
    fn prune(&mut self) {
        let late = self.latest_ns.saturating_sub(self.hold_ns);
        let keep_from = self.pending.front().map_or(late, |b| b.header.stamp_ns.saturating_sub(self.sync_ns).min(late));
        self.clouds.retain(|c| c.stamp() >= keep_from);
        for q in self.images.values_mut() {
            q.retain(|i| i.stamp() >= keep_from);
        }
    }

    /// Messages held now (for tests and the memory bound).
    pub fn held(&self) -> usize {
        self.clouds.len() + self.images.values().map(VecDeque::len).sum::<usize>() + self.pending.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(ms: i64) -> Header {
        Header { stamp_ns: ms * 1_000_000, frame_id: "f".into() }
    }

    fn cloud(ms: i64) -> PointCloud2 {
        PointCloud2 {
            header: header(ms),
            height: 1,
            width: 0,
            fields: vec![],
            is_bigendian: false,
            point_step: 12,
            row_step: 0,
            data: vec![],
        }
    }

    fn image(topic: &str, ms: i64) -> CameraImage {
        CameraImage { topic: topic.into(), header: header(ms), payload: ImagePayload::Encoded(vec![]) }
    }

    fn boxes(ms: i64) -> Detection3DArray {
        Detection3DArray { header: header(ms), detections: vec![] }
    }

    fn stamps(a: &Assembled) -> (i64, Option<i64>, Vec<(String, i64)>) {
        (
            a.boxes.header.stamp_ns / 1_000_000,
            a.cloud.as_ref().map(|(_, c)| c.header.stamp_ns / 1_000_000),
            a.images.iter().map(|i| (i.topic.clone(), i.header.stamp_ns / 1_000_000)).collect(),
        )
    }

    #[test]
    fn each_frame_takes_the_nearest_message_per_topic_within_the_window() {
        let mut s = Assembler::new(50.0);
        s.push_cloud("/lidar", cloud(0));
        s.push_image(image("/front", 30));
        s.push_image(image("/side", -45));
        assert!(s.push_boxes(boxes(5)).is_empty());
        // nothing later than 5 + 50 ms (and the reordering allowance) yet: the frame waits for a
        // nearer image
        s.push_cloud("/lidar", cloud(100));
        assert!(s.ready(false).is_empty());
        s.push_image(image("/front", 10));
        s.push_cloud("/lidar", cloud(600));
        let out = s.ready(false);
        assert_eq!(out.len(), 1);
        assert_eq!(stamps(&out[0]), (5, Some(0), vec![("/front".into(), 10), ("/side".into(), -45)]));
    }

    #[test]
    fn the_nearest_is_taken_even_when_an_earlier_one_is_in_the_window() {
        let mut s = Assembler::new(50.0);
        s.push_image(image("/front", 1_000 - 40));
        s.push_image(image("/front", 1_000 + 5));
        s.push_cloud("/top", cloud(1_000 - 30));
        s.push_cloud("/top", cloud(1_000 + 2));
        s.push_boxes(boxes(1_000));
        let out = s.ready(true);
        assert_eq!(stamps(&out[0]), (1_000, Some(1_002), vec![("/front".into(), 1_005)]));
        assert_eq!(out[0].cloud.as_ref().map(|(t, _)| t.as_str()), Some("/top"));
    }

    #[test]
    fn messages_outside_the_window_are_not_taken() {
        let mut s = Assembler::new(20.0);
        s.push_cloud("/lidar", cloud(0));
        s.push_image(image("/front", 75));
        s.push_boxes(boxes(50));
        let out = s.ready(true);
        assert_eq!(stamps(&out[0]), (50, None, vec![]));
    }

    #[test]
    fn frames_come_out_in_order_and_the_end_flushes_them() {
        let mut s = Assembler::new(50.0);
        for t in [0, 100, 200] {
            s.push_cloud("/lidar", cloud(t));
            s.push_boxes(boxes(t));
        }
        s.push_cloud("/lidar", cloud(700));
        let first: Vec<i64> = s.ready(false).iter().map(|a| stamps(a).0).collect();
        assert_eq!(first, vec![0, 100]);
        let rest: Vec<_> = s.ready(true).iter().map(stamps).collect();
        assert_eq!(rest, vec![(200, Some(200), vec![])]);
        assert!(s.ready(true).is_empty());
    }

    #[test]
    fn boxes_that_arrive_after_later_sweeps_still_get_their_own() {
        // a detector 300 ms behind the LiDAR, and a sync window shorter than the camera's lag
        let mut s = Assembler::new(2.0);
        let mut out = Vec::new();
        for t in 0..10 {
            s.push_cloud("/lidar", cloud(t * 100));
            s.push_image(image("/front", t * 100 + 1));
            if t >= 3 {
                out.extend(s.push_boxes(boxes((t - 3) * 100)));
            }
            out.extend(s.ready(false));
        }
        out.extend(s.ready(true));
        let got: Vec<_> = out.iter().map(stamps).collect();
        let want: Vec<_> = (0..7).map(|t| (t * 100, Some(t * 100), vec![("/front".to_owned(), t * 100 + 1)])).collect();
        assert_eq!(got, want);
    }

    #[test]
    fn memory_stays_bounded_on_a_long_log() {
        let mut s = Assembler::new(50.0);
        for t in 0..10_000 {
            s.push_cloud("/lidar", cloud(t * 100));
            s.push_image(image("/front", t * 100 + 3));
            s.push_boxes(boxes(t * 100));
            s.ready(false);
            // 10 Hz: the 550 ms held of two topics, and the frames waiting for them
            assert!(s.held() <= 3 * 7, "{t}: {}", s.held());
        }
        // stamps that never move on: the bound still holds, and the oldest frames come out
        let mut s = Assembler::new(50.0);
        let mut answered = 0;
        for _ in 0..1000 {
            s.push_cloud("/lidar", cloud(0));
            answered += s.push_boxes(boxes(0)).len();
            answered += s.ready(false).len();
        }
        assert!(s.held() <= 2 * MAX_BUFFERED, "{}", s.held());
        let waiting = s.ready(true).len();
        assert_eq!(waiting, MAX_BUFFERED);
        assert_eq!(answered + waiting, 1000);
    }
}
