//! The ROS 2 messages a drive log is read from, with their CDR layouts and the `ros2msg`
//! definitions written into logs (rosbag2's format: the message's own definition, then each
//! nested type after a line of 80 `=` and `MSG: pkg/Type`). Layouts are those of ROS 2 Humble
//! and later (vision_msgs 4).

use super::cdr::{CdrReader, CdrResult, CdrWriter};

/// `builtin_interfaces/msg/Time` as nanoseconds, and `std_msgs/msg/Header`'s frame id.
#[derive(Debug, Clone, PartialEq)]
pub struct Header {
    pub stamp_ns: i64,
    pub frame_id: String,
}

impl Header {
    fn read(r: &mut CdrReader) -> CdrResult<Header> {
        let sec = r.i32()?;
        let nanosec = r.u32()?;
        Ok(Header { stamp_ns: i64::from(sec) * 1_000_000_000 + i64::from(nanosec), frame_id: r.string()? })
    }

    fn write(&self, w: &mut CdrWriter) {
        let sec = self.stamp_ns.div_euclid(1_000_000_000);
        w.i32(sec as i32);
        w.u32(self.stamp_ns.rem_euclid(1_000_000_000) as u32);
        w.string(&self.frame_id);
    }
}

/// `sensor_msgs/msg/CompressedImage`.
#[derive(Debug, Clone, PartialEq)]
pub struct CompressedImage {
    pub header: Header,
    pub format: String,
    pub data: Vec<u8>,
}

/// `sensor_msgs/msg/Image`.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub is_bigendian: bool,
    pub step: u32,
    pub data: Vec<u8>,
}

/// `sensor_msgs/msg/CameraInfo` (binning and ROI kept to refuse them).
#[derive(Debug, Clone, PartialEq)]
pub struct CameraInfo {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub distortion_model: String,
    pub d: Vec<f64>,
    pub k: [f64; 9],
    pub binning: [u32; 2],
    /// x_offset, y_offset, height, width.
    pub roi: [u32; 4],
}

/// `sensor_msgs/msg/PointField`.
#[derive(Debug, Clone, PartialEq)]
pub struct PointField {
    pub name: String,
    pub offset: u32,
    pub datatype: u8,
    pub count: u32,
}

/// `PointField.FLOAT32`.
pub const FLOAT32: u8 = 7;

/// `sensor_msgs/msg/PointCloud2`.
#[derive(Debug, Clone, PartialEq)]
pub struct PointCloud2 {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub fields: Vec<PointField>,
    pub is_bigendian: bool,
    pub point_step: u32,
    pub row_step: u32,
    pub data: Vec<u8>,
}

/// A rigid transform: translation and unit quaternion `[x, y, z, w]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub translation: [f64; 3],
    pub rotation: [f64; 4],
}

/// `geometry_msgs/msg/TransformStamped`: `child` in `header.frame_id`.
#[derive(Debug, Clone, PartialEq)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Pose,
}

/// `vision_msgs/msg/Detection3D`: its hypotheses' classes, its box and its id.
#[derive(Debug, Clone, PartialEq)]
pub struct Detection3D {
    pub classes: Vec<(String, f64)>,
    pub center: Pose,
    /// Along the box's x (length), y (width), z (height).
    pub size: [f64; 3],
    pub id: String,
}

/// `vision_msgs/msg/Detection3DArray`.
#[derive(Debug, Clone, PartialEq)]
pub struct Detection3DArray {
    pub header: Header,
    pub detections: Vec<Detection3D>,
}

fn read_pose(r: &mut CdrReader) -> CdrResult<Pose> {
    Ok(Pose { translation: r.f64s()?, rotation: r.f64s()? })
}

fn write_pose(w: &mut CdrWriter, p: &Pose) {
    w.f64s(&p.translation);
    w.f64s(&p.rotation);
}

impl CompressedImage {
    pub fn decode(data: &[u8]) -> CdrResult<Self> {
        let r = &mut CdrReader::new(data)?;
        Ok(CompressedImage { header: Header::read(r)?, format: r.string()?, data: r.bytes()?.to_vec() })
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut w = CdrWriter::default();
        self.header.write(&mut w);
        w.string(&self.format);
        w.bytes(&self.data);
        w.finish()
    }
}

impl Image {
    pub fn decode(data: &[u8]) -> CdrResult<Self> {
        let r = &mut CdrReader::new(data)?;
        Ok(Image {
            header: Header::read(r)?,
            height: r.u32()?,
            width: r.u32()?,
            encoding: r.string()?,
            is_bigendian: r.u8()? != 0,
            step: r.u32()?,
            data: r.bytes()?.to_vec(),
        })
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut w = CdrWriter::default();
        self.header.write(&mut w);
        w.u32(self.height);
        w.u32(self.width);
        w.string(&self.encoding);
        w.u8(u8::from(self.is_bigendian));
        w.u32(self.step);
        w.bytes(&self.data);
        w.finish()
    }
}

impl CameraInfo {
    pub fn decode(data: &[u8]) -> CdrResult<Self> {
        let r = &mut CdrReader::new(data)?;
        let header = Header::read(r)?;
        let (height, width) = (r.u32()?, r.u32()?);
        let distortion_model = r.string()?;
        let d = r.f64_seq()?;
        let k = r.f64s()?;
        let _r: [f64; 9] = r.f64s()?;
        let _p: [f64; 12] = r.f64s()?;
        let binning = [r.u32()?, r.u32()?];
        let roi = [r.u32()?, r.u32()?, r.u32()?, r.u32()?];
        let _do_rectify = r.bool()?;
        Ok(CameraInfo { header, height, width, distortion_model, d, k, binning, roi })
    }

    /// With R the identity and P = [K | 0], as for a camera that is not rectified.
    pub fn encode(&self) -> Vec<u8> {
        let mut w = CdrWriter::default();
        self.header.write(&mut w);
        w.u32(self.height);
        w.u32(self.width);
        w.string(&self.distortion_model);
        w.f64_seq(&self.d);
        w.f64s(&self.k);
        w.f64s(&[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
        let k = &self.k;
        w.f64s(&[k[0], k[1], k[2], 0.0, k[3], k[4], k[5], 0.0, k[6], k[7], k[8], 0.0]);
        w.u32(self.binning[0]);
        w.u32(self.binning[1]);
        for v in self.roi {
            w.u32(v);
        }
        w.bool(false);
        w.finish()
    }
}

impl PointCloud2 {
    pub fn decode(data: &[u8]) -> CdrResult<Self> {
        let r = &mut CdrReader::new(data)?;
        let header = Header::read(r)?;
        let (height, width) = (r.u32()?, r.u32()?);
        let n = r.len(13)?;
        let fields = (0..n)
            .map(|_| Ok(PointField { name: r.string()?, offset: r.u32()?, datatype: r.u8()?, count: r.u32()? }))
            .collect::<CdrResult<Vec<_>>>()?;
        Ok(PointCloud2 {
            header,
            height,
            width,
            fields,
            is_bigendian: r.bool()?,
            point_step: r.u32()?,
            row_step: r.u32()?,
            data: r.bytes()?.to_vec(),
        })
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut w = CdrWriter::default();
        self.header.write(&mut w);
        w.u32(self.height);
        w.u32(self.width);
        w.u32(self.fields.len() as u32);
        for f in &self.fields {
            w.string(&f.name);
            w.u32(f.offset);
            w.u8(f.datatype);
            w.u32(f.count);
        }
        w.bool(self.is_bigendian);
        w.u32(self.point_step);
        w.u32(self.row_step);
        w.bytes(&self.data);
        w.bool(true);
        w.finish()
    }
}

/// `tf2_msgs/msg/TFMessage`.
pub fn decode_tf(data: &[u8]) -> CdrResult<Vec<TransformStamped>> {
    let r = &mut CdrReader::new(data)?;
    let n = r.len(4 + 4 + 4 + 4 + 7 * 8)?;
    (0..n)
        .map(|_| {
            Ok(TransformStamped { header: Header::read(r)?, child_frame_id: r.string()?, transform: read_pose(r)? })
        })
        .collect()
}

pub fn encode_tf(transforms: &[TransformStamped]) -> Vec<u8> {
    let mut w = CdrWriter::default();
    w.u32(transforms.len() as u32);
    for t in transforms {
        t.header.write(&mut w);
        w.string(&t.child_frame_id);
        write_pose(&mut w, &t.transform);
    }
    w.finish()
}

impl Detection3DArray {
    pub fn decode(data: &[u8]) -> CdrResult<Self> {
        let r = &mut CdrReader::new(data)?;
        let header = Header::read(r)?;
        let n = r.len(8)?;
        let detections = (0..n)
            .map(|_| {
                let _header = Header::read(r)?;
                let m = r.len(8)?;
                let classes = (0..m)
                    .map(|_| {
                        let class = (r.string()?, r.f64()?);
                        let _pose = read_pose(r)?;
                        let _covariance: [f64; 36] = r.f64s()?;
                        Ok(class)
                    })
                    .collect::<CdrResult<Vec<_>>>()?;
                Ok(Detection3D { classes, center: read_pose(r)?, size: r.f64s()?, id: r.string()? })
            })
            .collect::<CdrResult<Vec<_>>>()?;
        Ok(Detection3DArray { header, detections })
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut w = CdrWriter::default();
        self.header.write(&mut w);
        w.u32(self.detections.len() as u32);
        for d in &self.detections {
            self.header.write(&mut w);
            w.u32(d.classes.len() as u32);
            for (class, score) in &d.classes {
                w.string(class);
                w.f64(*score);
                write_pose(&mut w, &d.center);
                w.f64s(&[0.0; 36]);
            }
            write_pose(&mut w, &d.center);
            w.f64s(&d.size);
            w.string(&d.id);
        }
        w.finish()
    }
}

/// Schema names (as rosbag2 records them).
pub mod schema {
    pub const COMPRESSED_IMAGE: &str = "sensor_msgs/msg/CompressedImage";
    pub const IMAGE: &str = "sensor_msgs/msg/Image";
    pub const CAMERA_INFO: &str = "sensor_msgs/msg/CameraInfo";
    pub const POINT_CLOUD2: &str = "sensor_msgs/msg/PointCloud2";
    pub const TF_MESSAGE: &str = "tf2_msgs/msg/TFMessage";
    pub const DETECTION3D_ARRAY: &str = "vision_msgs/msg/Detection3DArray";
}

const TIME: &str = "int32 sec\nuint32 nanosec\n";
const HEADER: &str = "builtin_interfaces/Time stamp\nstring frame_id\n";
const POSE: &str = "Point position\nQuaternion orientation\n";
const POINT: &str = "float64 x\nfloat64 y\nfloat64 z\n";
const QUATERNION: &str = "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n";

fn definition(own: &str, nested: &[(&str, &str)]) -> String {
    let mut s = own.to_owned();
    for (name, text) in nested {
        s.push_str(&format!("{}\nMSG: {name}\n{text}", "=".repeat(80)));
    }
    s
}

/// The `ros2msg` definition of a schema this module writes.
pub fn ros2msg(schema_name: &str) -> Option<String> {
    let header = [("std_msgs/Header", HEADER), ("builtin_interfaces/Time", TIME)];
    Some(match schema_name {
        schema::COMPRESSED_IMAGE => definition("std_msgs/Header header\nstring format\nuint8[] data\n", &header),
        schema::IMAGE => definition(
            "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n",
            &header,
        ),
        schema::CAMERA_INFO => definition(
            "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\nsensor_msgs/RegionOfInterest roi\n",
            &[
                header[0],
                header[1],
                (
                    "sensor_msgs/RegionOfInterest",
                    "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n",
                ),
            ],
        ),
        schema::POINT_CLOUD2 => definition(
            "std_msgs/Header header\nuint32 height\nuint32 width\nsensor_msgs/PointField[] fields\nbool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n",
            &[
                header[0],
                header[1],
                (
                    "sensor_msgs/PointField",
                    "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\nuint8 UINT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\nstring name\nuint32 offset\nuint8 datatype\nuint32 count\n",
                ),
            ],
        ),
        schema::TF_MESSAGE => definition(
            "geometry_msgs/TransformStamped[] transforms\n",
            &[
                (
                    "geometry_msgs/TransformStamped",
                    "std_msgs/Header header\nstring child_frame_id\nTransform transform\n",
                ),
                header[0],
                header[1],
                ("geometry_msgs/Transform", "Vector3 translation\nQuaternion rotation\n"),
                ("geometry_msgs/Vector3", POINT),
                ("geometry_msgs/Quaternion", QUATERNION),
            ],
        ),
        schema::DETECTION3D_ARRAY => definition(
            "std_msgs/Header header\nDetection3D[] detections\n",
            &[
                header[0],
                header[1],
                (
                    "vision_msgs/Detection3D",
                    "std_msgs/Header header\nObjectHypothesisWithPose[] results\nBoundingBox3D bbox\nstring id\n",
                ),
                (
                    "vision_msgs/ObjectHypothesisWithPose",
                    "ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n",
                ),
                ("vision_msgs/ObjectHypothesis", "string class_id\nfloat64 score\n"),
                ("geometry_msgs/PoseWithCovariance", "Pose pose\nfloat64[36] covariance\n"),
                ("geometry_msgs/Pose", POSE),
                ("geometry_msgs/Point", POINT),
                ("geometry_msgs/Quaternion", QUATERNION),
                ("vision_msgs/BoundingBox3D", "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n"),
                ("geometry_msgs/Vector3", POINT),
            ],
        ),
        _ => return None,
    })
}

/// Whether a log's `vision_msgs/msg/Detection3DArray` definition has the layout read here
/// (vision_msgs 4, ROS 2 Humble and later; earlier ones carried a point cloud per detection).
pub fn detection_layout_supported(definition: &str) -> bool {
    definition.contains("ObjectHypothesis hypothesis") && !definition.contains("source_cloud")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header() -> Header {
        Header { stamp_ns: 1_700_000_000_123_456_789, frame_id: "cam".into() }
    }

    #[test]
    fn every_message_decodes_as_it_was_encoded() {
        let c = CompressedImage { header: header(), format: "jpeg".into(), data: vec![1, 2, 3] };
        assert_eq!(CompressedImage::decode(&c.encode()).unwrap(), c);
        let i = Image {
            header: header(),
            height: 2,
            width: 1,
            encoding: "rgb8".into(),
            is_bigendian: false,
            step: 3,
            data: vec![9; 6],
        };
        assert_eq!(Image::decode(&i.encode()).unwrap(), i);
        let ci = CameraInfo {
            header: header(),
            height: 4,
            width: 6,
            distortion_model: "plumb_bob".into(),
            d: vec![0.1, -0.2, 0.0, 0.0, 0.01],
            k: [100.0, 0.0, 3.0, 0.0, 101.0, 2.0, 0.0, 0.0, 1.0],
            binning: [0, 0],
            roi: [0; 4],
        };
        assert_eq!(CameraInfo::decode(&ci.encode()).unwrap(), ci);
        let pc = PointCloud2 {
            header: header(),
            height: 1,
            width: 1,
            fields: vec![PointField { name: "x".into(), offset: 0, datatype: FLOAT32, count: 1 }],
            is_bigendian: false,
            point_step: 4,
            row_step: 4,
            data: vec![0, 0, 128, 63],
        };
        assert_eq!(PointCloud2::decode(&pc.encode()).unwrap(), pc);
        let pose = Pose { translation: [1.0, 2.0, 3.0], rotation: [0.0, 0.0, 0.6, 0.8] };
        let tf = vec![TransformStamped { header: header(), child_frame_id: "lidar".into(), transform: pose }];
        assert_eq!(decode_tf(&encode_tf(&tf)).unwrap(), tf);
        let d = Detection3DArray {
            header: header(),
            detections: vec![Detection3D {
                classes: vec![("pedestrian".into(), 0.9), ("cyclist".into(), 0.1)],
                center: pose,
                size: [0.8, 0.6, 1.7],
                id: "17".into(),
            }],
        };
        assert_eq!(Detection3DArray::decode(&d.encode()).unwrap(), d);
    }

    #[test]
    fn negative_stamps_keep_their_nanoseconds_positive() {
        let h = Header { stamp_ns: -1, frame_id: String::new() };
        let mut w = CdrWriter::default();
        h.write(&mut w);
        let b = w.finish();
        assert_eq!(&b[4..12], &[255, 255, 255, 255, 0xff, 0xc9, 0x9a, 0x3b]);
        assert_eq!(Header::read(&mut CdrReader::new(&b).unwrap()).unwrap(), h);
    }

    #[test]
    fn a_truncated_message_is_an_error_not_a_panic() {
        let c = CompressedImage { header: header(), format: "jpeg".into(), data: vec![7; 100] }.encode();
        for cut in 0..c.len() {
            assert!(CompressedImage::decode(&c[..cut]).is_err(), "cut at {cut}");
        }
    }

    #[test]
    fn definitions_list_their_nested_types() {
        let d = ros2msg(schema::DETECTION3D_ARRAY).unwrap();
        assert!(d.starts_with("std_msgs/Header header\nDetection3D[] detections\n"));
        assert!(d.contains("\nMSG: vision_msgs/ObjectHypothesis\nstring class_id\nfloat64 score\n"));
        assert!(detection_layout_supported(&d));
        assert!(!detection_layout_supported("std_msgs/Header header\nsensor_msgs/PointCloud2 source_cloud\n"));
        assert!(ros2msg("foo/msg/Bar").is_none());
    }
}
