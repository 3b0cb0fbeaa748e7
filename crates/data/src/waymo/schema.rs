//! Component and column names of the v2 layout, and the enums posefuse uses.

use posefuse_core::keypoints::K;

/// Camera names (`key.camera_name`), in enum order 1..=5.
pub const CAMERA_NAMES: [&str; 5] = ["FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT"];
/// Laser names (`key.laser_name`), in enum order 1..=5.
pub const LASER_NAMES: [&str; 5] = ["TOP", "FRONT", "SIDE_LEFT", "SIDE_RIGHT", "REAR"];
/// The TOP laser (the only one with per-pixel poses).
pub const LASER_TOP: i64 = 1;
/// `type` of a pedestrian box.
pub const TYPE_PEDESTRIAN: i64 = 2;
/// Keypoint types outside posefuse's 13 that labels carry.
pub const KP_FOREHEAD: i64 = 19;
pub const KP_HEAD_CENTER: i64 = 20;

/// Waymo keypoint type of each of posefuse's 13 keypoints (docs/ARCHITECTURE.md order).
pub const KEYPOINT_TYPES: [i64; K] = [1, 5, 13, 6, 14, 7, 15, 8, 16, 9, 17, 10, 18];

/// posefuse's index of a Waymo keypoint type (`None` for types outside the 13).
pub fn keypoint_index(kind: i64) -> Option<usize> {
    KEYPOINT_TYPES.iter().position(|&t| t == kind)
}

/// Enum value of a camera or laser name given as text (`"FRONT"`, or a number as text).
pub fn name_value(names: &[&str], s: &str) -> Option<i64> {
    let s = s.trim();
    names.iter().position(|n| n.eq_ignore_ascii_case(s)).map(|i| i as i64 + 1).or_else(|| s.parse().ok())
}

/// Components, as folder names under the dataset root.
pub mod comp {
    pub const CAMERA_IMAGE: &str = "camera_image";
    pub const CAMERA_CALIBRATION: &str = "camera_calibration";
    pub const LIDAR: &str = "lidar";
    pub const LIDAR_CALIBRATION: &str = "lidar_calibration";
    pub const LIDAR_POSE: &str = "lidar_pose";
    pub const VEHICLE_POSE: &str = "vehicle_pose";
    pub const LIDAR_BOX: &str = "lidar_box";
    pub const CAMERA_BOX: &str = "camera_box";
    pub const ASSOCIATION: &str = "camera_to_lidar_box_association";
    pub const CAMERA_HKP: &str = "camera_hkp";
    pub const LIDAR_HKP: &str = "lidar_hkp";
}

/// Key columns.
pub mod key {
    pub const SEGMENT: &str = "key.segment_context_name";
    pub const TIMESTAMP: &str = "key.frame_timestamp_micros";
    pub const CAMERA: &str = "key.camera_name";
    pub const LASER: &str = "key.laser_name";
    pub const CAMERA_OBJECT: &str = "key.camera_object_id";
    pub const LASER_OBJECT: &str = "key.laser_object_id";
}

/// Value columns (the ones posefuse reads or writes).
pub mod col {
    pub const IMAGE: &str = "[CameraImageComponent].image";
    pub const CAM_F_U: &str = "[CameraCalibrationComponent].intrinsic.f_u";
    pub const CAM_F_V: &str = "[CameraCalibrationComponent].intrinsic.f_v";
    pub const CAM_C_U: &str = "[CameraCalibrationComponent].intrinsic.c_u";
    pub const CAM_C_V: &str = "[CameraCalibrationComponent].intrinsic.c_v";
    pub const CAM_K1: &str = "[CameraCalibrationComponent].intrinsic.k1";
    pub const CAM_K2: &str = "[CameraCalibrationComponent].intrinsic.k2";
    pub const CAM_P1: &str = "[CameraCalibrationComponent].intrinsic.p1";
    pub const CAM_P2: &str = "[CameraCalibrationComponent].intrinsic.p2";
    pub const CAM_K3: &str = "[CameraCalibrationComponent].intrinsic.k3";
    /// The nine intrinsic columns in the order of `CameraCalibration::intrinsic`.
    pub const CAM_INTRINSIC: [&str; 9] = [CAM_F_U, CAM_F_V, CAM_C_U, CAM_C_V, CAM_K1, CAM_K2, CAM_P1, CAM_P2, CAM_K3];
    pub const CAM_EXTRINSIC: &str = "[CameraCalibrationComponent].extrinsic.transform";
    pub const CAM_WIDTH: &str = "[CameraCalibrationComponent].width";
    pub const CAM_HEIGHT: &str = "[CameraCalibrationComponent].height";
    pub const RI1_VALUES: &str = "[LiDARComponent].range_image_return1.values";
    pub const RI1_SHAPE: &str = "[LiDARComponent].range_image_return1.shape";
    pub const RI2_VALUES: &str = "[LiDARComponent].range_image_return2.values";
    pub const RI2_SHAPE: &str = "[LiDARComponent].range_image_return2.shape";
    pub const LASER_EXTRINSIC: &str = "[LiDARCalibrationComponent].extrinsic.transform";
    pub const INCL_MIN: &str = "[LiDARCalibrationComponent].beam_inclination.min";
    pub const INCL_MAX: &str = "[LiDARCalibrationComponent].beam_inclination.max";
    pub const INCL_VALUES: &str = "[LiDARCalibrationComponent].beam_inclination.values";
    pub const POSE_VALUES: &str = "[LiDARPoseComponent].range_image_return1.values";
    pub const POSE_SHAPE: &str = "[LiDARPoseComponent].range_image_return1.shape";
    pub const VEHICLE_POSE: &str = "[VehiclePoseComponent].world_from_vehicle.transform";
    pub const LBOX_CX: &str = "[LiDARBoxComponent].box.center.x";
    pub const LBOX_CY: &str = "[LiDARBoxComponent].box.center.y";
    pub const LBOX_CZ: &str = "[LiDARBoxComponent].box.center.z";
    pub const LBOX_SX: &str = "[LiDARBoxComponent].box.size.x";
    pub const LBOX_SY: &str = "[LiDARBoxComponent].box.size.y";
    pub const LBOX_SZ: &str = "[LiDARBoxComponent].box.size.z";
    pub const LBOX_HEADING: &str = "[LiDARBoxComponent].box.heading";
    pub const LBOX_TYPE: &str = "[LiDARBoxComponent].type";
    pub const CBOX_CX: &str = "[CameraBoxComponent].box.center.x";
    pub const CBOX_CY: &str = "[CameraBoxComponent].box.center.y";
    pub const CBOX_SX: &str = "[CameraBoxComponent].box.size.x";
    pub const CBOX_SY: &str = "[CameraBoxComponent].box.size.y";
    pub const CBOX_TYPE: &str = "[CameraBoxComponent].type";
    pub const CHKP_TYPE: &str = "[CameraHumanKeypointsComponent].camera_keypoints[*].type";
    pub const CHKP_X: &str = "[CameraHumanKeypointsComponent].camera_keypoints[*].keypoint_2d.location_px.x";
    pub const CHKP_Y: &str = "[CameraHumanKeypointsComponent].camera_keypoints[*].keypoint_2d.location_px.y";
    pub const CHKP_OCCLUDED: &str =
        "[CameraHumanKeypointsComponent].camera_keypoints[*].keypoint_2d.visibility.is_occluded";
    pub const LHKP_TYPE: &str = "[LiDARHumanKeypointsComponent].lidar_keypoints[*].type";
    pub const LHKP_X: &str = "[LiDARHumanKeypointsComponent].lidar_keypoints[*].keypoint_3d.location_m.x";
    pub const LHKP_Y: &str = "[LiDARHumanKeypointsComponent].lidar_keypoints[*].keypoint_3d.location_m.y";
    pub const LHKP_Z: &str = "[LiDARHumanKeypointsComponent].lidar_keypoints[*].keypoint_3d.location_m.z";
    pub const LHKP_OCCLUDED: &str =
        "[LiDARHumanKeypointsComponent].lidar_keypoints[*].keypoint_3d.visibility.is_occluded";
}
