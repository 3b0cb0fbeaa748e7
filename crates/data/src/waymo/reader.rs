//! One segment of a v2 dataset root, joined on the `key.*` columns.
//!
//! The small components (calibrations, poses, boxes, associations, keypoints) are read whole.
//! The large ones (`lidar`, `lidar_pose`, `camera_image`) are streamed: a first pass reads only
//! their key columns to know which rows each frame has, then their value columns are read a few
//! rows at a time, in file order, and a frame's rows are handed out as soon as they are all in.
//! Memory holds one frame's range images and images (plus rows read ahead of their frame when a
//! component's rows are in a different frame order than `lidar`'s).

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::path::{Path, PathBuf};

use crate::error::Context;
use crate::{ensure, invalid};
use parquet::arrow::arrow_reader::{ParquetRecordBatchReader, ParquetRecordBatchReaderBuilder};
use parquet::arrow::ProjectionMask;

use super::convert::{Kp2dLabel, Kp3dLabel};
use super::range::{mat4, LaserCalibration, Mat4, RangeImage};
use super::schema::{col, comp, key, CAMERA_NAMES, LASER_NAMES, TYPE_PEDESTRIAN};
use super::table::{component_path, read_columns, Table};
use posefuse_core::frame::{Box2d, Box3d, CameraCalibration};

/// Rows read at a time from a streamed component.
const STREAM_ROWS: usize = 4;

fn exists(root: &Path, component: &str, segment: &str) -> bool {
    component_path(root, component, segment).is_file()
}

fn require(root: &Path, component: &str, segment: &str) -> crate::error::Result<PathBuf> {
    let p = component_path(root, component, segment);
    ensure!(p.is_file(), "segment {segment}: component `{component}` is missing ({} not found)", p.display());
    Ok(p)
}

fn transform(v: &[f64], what: &str) -> crate::error::Result<Mat4> {
    ensure!(v.len() == 16, "{what}: {} numbers, not 16", v.len());
    Ok(mat4(&std::array::from_fn(|i| v[i])))
}

/// A pedestrian's 3D box.
#[derive(Debug, Clone)]
pub struct LidarBox {
    pub id: String,
    pub box3d: Box3d,
}

/// A camera box and the laser object it shows.
#[derive(Debug, Clone)]
pub struct CameraObject {
    pub camera: i64,
    pub id: String,
    pub box2d: Box2d,
    pub laser_object: Option<String>,
    pub keypoints: Option<Vec<Kp2dLabel>>,
}

/// The labels of one frame.
#[derive(Debug, Clone, Default)]
pub struct FrameLabels {
    pub pedestrians: Vec<LidarBox>,
    pub camera_objects: Vec<CameraObject>,
    /// `lidar_hkp` by laser object id.
    pub lidar_keypoints: HashMap<String, Vec<Kp3dLabel>>,
}

/// One laser's data of a frame.
#[derive(Debug, Clone)]
pub struct LaserFrame {
    pub name: i64,
    pub returns: [RangeImage; 2],
    /// TOP only: per-pixel vehicle poses.
    pub pixel_poses: Option<RangeImage>,
}

/// The sensor data of one frame.
#[derive(Debug, Clone)]
pub struct FrameData {
    pub timestamp: i64,
    pub vehicle_pose: Option<Mat4>,
    pub lasers: Vec<LaserFrame>,
    /// Camera name → JPEG bytes.
    pub images: BTreeMap<i64, Vec<u8>>,
}

/// A component read a few rows at a time, in file order.
struct Stream {
    component: &'static str,
    name_col: &'static str,
    names: &'static [&'static str],
    reader: ParquetRecordBatchReader,
    /// Rows each timestamp has.
    expected: HashMap<i64, usize>,
    /// Rows read, by timestamp: (name, the row's table and index).
    pending: HashMap<i64, Vec<(i64, Table, usize)>>,
}

impl Stream {
    fn open(
        path: &Path,
        component: &'static str,
        name_col: &'static str,
        names: &'static [&'static str],
        values: &[&str],
    ) -> crate::error::Result<Stream> {
        let keys = read_columns(path, component, &[key::TIMESTAMP], None)?;
        let mut expected = HashMap::new();
        for ts in keys.i64s(key::TIMESTAMP)? {
            *expected.entry(ts).or_insert(0) += 1;
        }
        let file = File::open(path).with_context(|| format!("component `{component}`: {}", path.display()))?;
        let b = ParquetRecordBatchReaderBuilder::try_new(file)
            .with_context(|| format!("component `{component}`: {}", path.display()))?;
        let fields = b.schema().fields().clone();
        let mut roots = Vec::new();
        for c in [key::TIMESTAMP, name_col].iter().chain(values) {
            roots.push(
                fields
                    .iter()
                    .position(|f| f.name() == c)
                    .ok_or_else(|| invalid!("component `{component}` ({}): no column `{c}`", path.display()))?,
            );
        }
        let mask = ProjectionMask::roots(b.parquet_schema(), roots);
        let reader = b.with_projection(mask).with_batch_size(STREAM_ROWS).build()?;
        Ok(Stream { component, name_col, names, reader, expected, pending: HashMap::new() })
    }

    /// All rows of timestamp `ts` (name, table, row), reading ahead as needed.
    fn take(&mut self, ts: i64) -> crate::error::Result<Vec<(i64, Table, usize)>> {
        let want = self.expected.get(&ts).copied().unwrap_or(0);
        while self.pending.get(&ts).map_or(0, Vec::len) < want {
            let batch = self
                .reader
                .next()
                .ok_or_else(|| invalid!("component `{}`: rows of frame {ts} missing", self.component))?
                .with_context(|| format!("component `{}`: decoding", self.component))?;
            let t = Table { component: self.component.to_owned(), batch };
            let tss = t.i64s(key::TIMESTAMP)?;
            let names = t.enums(self.name_col, self.names)?;
            for (i, (ts_i, n)) in tss.into_iter().zip(names).enumerate() {
                let single = Table { component: t.component.clone(), batch: t.batch.slice(i, 1) };
                self.pending.entry(ts_i).or_default().push((n, single, 0));
            }
        }
        Ok(self.pending.remove(&ts).unwrap_or_default())
    }
}

/// One segment, opened.
pub struct Segment {
    pub name: String,
    pub root: PathBuf,
    /// Frame timestamps, in time order (those of the `lidar` component).
    pub timestamps: Vec<i64>,
    pub cameras: BTreeMap<i64, CameraCalibration>,
    pub lasers: BTreeMap<i64, LaserCalibration>,
    pub vehicle_poses: HashMap<i64, Mat4>,
    pub has_camera_hkp: bool,
    pub has_lidar_hkp: bool,
    labels: HashMap<i64, FrameLabels>,
    lidar: Stream,
    lidar_pose: Option<Stream>,
    images: Option<Stream>,
}

/// Which cameras to read (`None`: all).
pub type CameraFilter = Option<Vec<i64>>;

impl Segment {
    /// Opens a segment: reads the small components, indexes the large ones.
    pub fn open(root: &Path, name: &str, cameras_wanted: &CameraFilter) -> crate::error::Result<Segment> {
        let lidar_path = require(root, comp::LIDAR, name)?;
        let lcal = read_columns(
            &require(root, comp::LIDAR_CALIBRATION, name)?,
            comp::LIDAR_CALIBRATION,
            &[key::LASER, col::LASER_EXTRINSIC, col::INCL_MIN, col::INCL_MAX, col::INCL_VALUES],
            None,
        )?;
        let mut lasers = BTreeMap::new();
        let (names, ext, lo, hi, vals) = (
            lcal.enums(key::LASER, &LASER_NAMES)?,
            lcal.f64_lists(col::LASER_EXTRINSIC)?,
            lcal.f64s(col::INCL_MIN)?,
            lcal.f64s(col::INCL_MAX)?,
            lcal.f64_lists(col::INCL_VALUES)?,
        );
        for i in 0..lcal.rows() {
            ensure!(
                ext[i].len() == 16,
                "component `lidar_calibration`: extrinsic of laser {} has {} numbers",
                names[i],
                ext[i].len()
            );
            lasers.insert(
                names[i],
                LaserCalibration {
                    name: names[i],
                    extrinsic: std::array::from_fn(|k| ext[i][k]),
                    inclination_min: lo[i],
                    inclination_max: hi[i],
                    inclinations: vals[i].clone(),
                },
            );
        }
        let mut vehicle_poses = HashMap::new();
        if exists(root, comp::VEHICLE_POSE, name) {
            let t = read_columns(
                &component_path(root, comp::VEHICLE_POSE, name),
                comp::VEHICLE_POSE,
                &[key::TIMESTAMP, col::VEHICLE_POSE],
                None,
            )?;
            for (ts, m) in t.i64s(key::TIMESTAMP)?.into_iter().zip(t.f64_lists(col::VEHICLE_POSE)?) {
                vehicle_poses.insert(ts, transform(&m, "vehicle_pose")?);
            }
        }
        let mut cameras = BTreeMap::new();
        let with_cameras = exists(root, comp::CAMERA_CALIBRATION, name) && exists(root, comp::CAMERA_IMAGE, name);
        if with_cameras {
            let mut cols = vec![key::CAMERA, col::CAM_EXTRINSIC, col::CAM_WIDTH, col::CAM_HEIGHT];
            cols.extend(col::CAM_INTRINSIC);
            let t = read_columns(
                &component_path(root, comp::CAMERA_CALIBRATION, name),
                comp::CAMERA_CALIBRATION,
                &cols,
                None,
            )?;
            let names = t.enums(key::CAMERA, &CAMERA_NAMES)?;
            let intr: Vec<Vec<f64>> =
                col::CAM_INTRINSIC.iter().map(|c| t.f64s(c)).collect::<crate::error::Result<_>>()?;
            let (ext, w, h) = (t.f64_lists(col::CAM_EXTRINSIC)?, t.i64s(col::CAM_WIDTH)?, t.i64s(col::CAM_HEIGHT)?);
            for i in 0..t.rows() {
                if cameras_wanted.as_ref().is_some_and(|c| !c.contains(&names[i])) {
                    continue;
                }
                cameras.insert(
                    names[i],
                    CameraCalibration {
                        intrinsic: intr.iter().map(|c| c[i]).collect(),
                        extrinsic: ext[i].clone(),
                        width: w[i] as u32,
                        height: h[i] as u32,
                    },
                );
            }
        }
        let labels = read_labels(root, name, &cameras)?;
        let lidar = Stream::open(
            &lidar_path,
            comp::LIDAR,
            key::LASER,
            &LASER_NAMES,
            &[col::RI1_VALUES, col::RI1_SHAPE, col::RI2_VALUES, col::RI2_SHAPE],
        )?;
        let mut timestamps: Vec<i64> = lidar.expected.keys().copied().collect();
        timestamps.sort_unstable();
        let lidar_pose = if exists(root, comp::LIDAR_POSE, name) {
            Some(Stream::open(
                &component_path(root, comp::LIDAR_POSE, name),
                comp::LIDAR_POSE,
                key::LASER,
                &LASER_NAMES,
                &[col::POSE_VALUES, col::POSE_SHAPE],
            )?)
        } else {
            None
        };
        let images = if with_cameras {
            Some(Stream::open(
                &component_path(root, comp::CAMERA_IMAGE, name),
                comp::CAMERA_IMAGE,
                key::CAMERA,
                &CAMERA_NAMES,
                &[col::IMAGE],
            )?)
        } else {
            None
        };
        Ok(Segment {
            name: name.to_owned(),
            root: root.to_path_buf(),
            timestamps,
            cameras,
            lasers,
            vehicle_poses,
            has_camera_hkp: exists(root, comp::CAMERA_HKP, name),
            has_lidar_hkp: exists(root, comp::LIDAR_HKP, name),
            labels,
            lidar,
            lidar_pose,
            images,
        })
    }

    /// The labels of a frame (empty when it has none).
    pub fn labels(&self, ts: i64) -> FrameLabels {
        self.labels.get(&ts).cloned().unwrap_or_default()
    }

    /// The sensor data of frame `ts`; call in time order for bounded memory. `images`: which
    /// cameras' images to keep (the others are read past).
    pub fn frame(&mut self, ts: i64, images: &[i64]) -> crate::error::Result<FrameData> {
        let mut lasers = Vec::new();
        let mut poses: HashMap<i64, RangeImage> = HashMap::new();
        if let Some(s) = self.lidar_pose.as_mut() {
            for (n, t, i) in s.take(ts)? {
                let v = t.f32_lists(col::POSE_VALUES)?.swap_remove(i);
                let shape = t.i64_lists(col::POSE_SHAPE)?.swap_remove(i);
                poses
                    .insert(n, RangeImage::new(v, &shape).with_context(|| format!("lidar_pose of laser {n} at {ts}"))?);
            }
        }
        for (n, t, i) in self.lidar.take(ts)? {
            let ri = |vc: &str, sc: &str| -> crate::error::Result<RangeImage> {
                let v = t.f32_lists(vc)?.swap_remove(i);
                let shape = t.i64_lists(sc)?.swap_remove(i);
                RangeImage::new(v, &shape).with_context(|| format!("component `lidar`: `{vc}` of laser {n} at {ts}"))
            };
            let r1 = ri(col::RI1_VALUES, col::RI1_SHAPE)?;
            let r2 = ri(col::RI2_VALUES, col::RI2_SHAPE)?;
            lasers.push(LaserFrame { name: n, returns: [r1, r2], pixel_poses: poses.remove(&n) });
        }
        lasers.sort_by_key(|l| l.name);
        let mut out = BTreeMap::new();
        if let Some(s) = self.images.as_mut() {
            for (n, t, i) in s.take(ts)? {
                if images.contains(&n) {
                    out.insert(n, t.binaries(col::IMAGE)?.swap_remove(i));
                }
            }
        }
        Ok(FrameData { timestamp: ts, vehicle_pose: self.vehicle_poses.get(&ts).copied(), lasers, images: out })
    }
}

fn read_labels(
    root: &Path,
    name: &str,
    cameras: &BTreeMap<i64, CameraCalibration>,
) -> crate::error::Result<HashMap<i64, FrameLabels>> {
    let mut labels: HashMap<i64, FrameLabels> = HashMap::new();
    let t = read_columns(
        &require(root, comp::LIDAR_BOX, name)?,
        comp::LIDAR_BOX,
        &[
            key::TIMESTAMP,
            key::LASER_OBJECT,
            col::LBOX_CX,
            col::LBOX_CY,
            col::LBOX_CZ,
            col::LBOX_SX,
            col::LBOX_SY,
            col::LBOX_SZ,
            col::LBOX_HEADING,
            col::LBOX_TYPE,
        ],
        None,
    )?;
    let (ts, ids, kind) = (t.i64s(key::TIMESTAMP)?, t.strings(key::LASER_OBJECT)?, t.i64s(col::LBOX_TYPE)?);
    let g: Vec<Vec<f64>> =
        [col::LBOX_CX, col::LBOX_CY, col::LBOX_CZ, col::LBOX_SX, col::LBOX_SY, col::LBOX_SZ, col::LBOX_HEADING]
            .iter()
            .map(|c| t.f64s(c))
            .collect::<crate::error::Result<_>>()?;
    for i in 0..t.rows() {
        if kind[i] != TYPE_PEDESTRIAN {
            continue;
        }
        let box3d = Box3d {
            center_x: g[0][i],
            center_y: g[1][i],
            center_z: g[2][i],
            length: g[3][i],
            width: g[4][i],
            height: g[5][i],
            heading: g[6][i],
        };
        labels.entry(ts[i]).or_default().pedestrians.push(LidarBox { id: ids[i].clone(), box3d });
    }
    if exists(root, comp::LIDAR_HKP, name) {
        let t = read_columns(
            &component_path(root, comp::LIDAR_HKP, name),
            comp::LIDAR_HKP,
            &[key::TIMESTAMP, key::LASER_OBJECT, col::LHKP_TYPE, col::LHKP_X, col::LHKP_Y, col::LHKP_Z],
            None,
        )?;
        // `is_occluded` is informational: a release without it still has keypoints.
        let occ =
            read_columns(&component_path(root, comp::LIDAR_HKP, name), comp::LIDAR_HKP, &[col::LHKP_OCCLUDED], None)
                .ok();
        let occ = match occ {
            Some(o) => Some(o.bool_lists(col::LHKP_OCCLUDED)?),
            None => None,
        };
        let (ts, ids, kinds) = (t.i64s(key::TIMESTAMP)?, t.strings(key::LASER_OBJECT)?, t.i64_lists(col::LHKP_TYPE)?);
        let (x, y, z) = (t.f64_lists(col::LHKP_X)?, t.f64_lists(col::LHKP_Y)?, t.f64_lists(col::LHKP_Z)?);
        for i in 0..t.rows() {
            let n = kinds[i].len();
            ensure!(
                x[i].len() == n && y[i].len() == n && z[i].len() == n,
                "component `lidar_hkp`: row {i} has {n} types but {}/{}/{} coordinates",
                x[i].len(),
                y[i].len(),
                z[i].len()
            );
            let kps = (0..n)
                .map(|k| Kp3dLabel {
                    kind: kinds[i][k],
                    xyz: [x[i][k], y[i][k], z[i][k]],
                    occluded: occ.as_ref().and_then(|o| o[i].get(k).copied()).unwrap_or(false),
                })
                .collect();
            labels.entry(ts[i]).or_default().lidar_keypoints.insert(ids[i].clone(), kps);
        }
    }
    if cameras.is_empty() || !exists(root, comp::CAMERA_BOX, name) {
        return Ok(labels);
    }
    let t = read_columns(
        &component_path(root, comp::CAMERA_BOX, name),
        comp::CAMERA_BOX,
        &[
            key::TIMESTAMP,
            key::CAMERA,
            key::CAMERA_OBJECT,
            col::CBOX_CX,
            col::CBOX_CY,
            col::CBOX_SX,
            col::CBOX_SY,
            col::CBOX_TYPE,
        ],
        None,
    )?;
    let (ts, cams, ids, kind) = (
        t.i64s(key::TIMESTAMP)?,
        t.enums(key::CAMERA, &CAMERA_NAMES)?,
        t.strings(key::CAMERA_OBJECT)?,
        t.i64s(col::CBOX_TYPE)?,
    );
    let g: Vec<Vec<f64>> = [col::CBOX_CX, col::CBOX_CY, col::CBOX_SX, col::CBOX_SY]
        .iter()
        .map(|c| t.f64s(c))
        .collect::<crate::error::Result<_>>()?;
    let mut assoc: HashMap<(i64, i64, String), String> = HashMap::new();
    if exists(root, comp::ASSOCIATION, name) {
        let a = read_columns(
            &component_path(root, comp::ASSOCIATION, name),
            comp::ASSOCIATION,
            &[key::TIMESTAMP, key::CAMERA, key::CAMERA_OBJECT, key::LASER_OBJECT],
            None,
        )?;
        let (ats, acam, aco, alo) = (
            a.i64s(key::TIMESTAMP)?,
            a.enums(key::CAMERA, &CAMERA_NAMES)?,
            a.strings(key::CAMERA_OBJECT)?,
            a.strings(key::LASER_OBJECT)?,
        );
        for i in 0..a.rows() {
            assoc.insert((ats[i], acam[i], aco[i].clone()), alo[i].clone());
        }
    }
    let mut hkp: HashMap<(i64, i64, String), Vec<Kp2dLabel>> = HashMap::new();
    if exists(root, comp::CAMERA_HKP, name) {
        let p = component_path(root, comp::CAMERA_HKP, name);
        let h = read_columns(
            &p,
            comp::CAMERA_HKP,
            &[key::TIMESTAMP, key::CAMERA, key::CAMERA_OBJECT, col::CHKP_TYPE, col::CHKP_X, col::CHKP_Y],
            None,
        )?;
        let occ = read_columns(&p, comp::CAMERA_HKP, &[col::CHKP_OCCLUDED], None).ok();
        let occ = match occ {
            Some(o) => Some(o.bool_lists(col::CHKP_OCCLUDED)?),
            None => None,
        };
        let (hts, hcam, hid) =
            (h.i64s(key::TIMESTAMP)?, h.enums(key::CAMERA, &CAMERA_NAMES)?, h.strings(key::CAMERA_OBJECT)?);
        let (kinds, x, y) = (h.i64_lists(col::CHKP_TYPE)?, h.f64_lists(col::CHKP_X)?, h.f64_lists(col::CHKP_Y)?);
        for i in 0..h.rows() {
            let n = kinds[i].len();
            ensure!(
                x[i].len() == n && y[i].len() == n,
                "component `camera_hkp`: row {i} has {n} types but {}/{} coordinates",
                x[i].len(),
                y[i].len()
            );
            let kps = (0..n)
                .map(|k| Kp2dLabel {
                    kind: kinds[i][k],
                    uv: [x[i][k], y[i][k]],
                    occluded: occ.as_ref().and_then(|o| o[i].get(k).copied()).unwrap_or(false),
                })
                .collect();
            hkp.insert((hts[i], hcam[i], hid[i].clone()), kps);
        }
    }
    for i in 0..t.rows() {
        if kind[i] != TYPE_PEDESTRIAN || !cameras.contains_key(&cams[i]) {
            continue;
        }
        let k = (ts[i], cams[i], ids[i].clone());
        labels.entry(ts[i]).or_default().camera_objects.push(CameraObject {
            camera: cams[i],
            id: ids[i].clone(),
            box2d: Box2d { center_x: g[0][i], center_y: g[1][i], width: g[2][i], height: g[3][i] },
            laser_object: assoc.get(&k).cloned(),
            keypoints: hkp.remove(&k),
        });
    }
    Ok(labels)
}
