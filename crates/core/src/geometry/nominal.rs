//! The nominal front camera: the simulator's camera without mounting or lens variation, and the
//! calibration real-data readers fall back to when a frame carries none.

use crate::error::Result;
use crate::frame::CameraCalibration;

use super::Camera;

/// The camera without mounting or lens variation (tests, examples, calibration fallbacks).
pub fn nominal_camera() -> Result<Camera> {
    let t = [1.58, -0.04, 1.92];
    Camera::from_calibration(&CameraCalibration {
        intrinsic: vec![2040.0, 2040.0, 960.0, 640.0, 0.05, -0.005, 0.0, 0.0, 0.0],
        extrinsic: vec![1.0, 0.0, 0.0, t[0], 0.0, 1.0, 0.0, t[1], 0.0, 0.0, 1.0, t[2], 0.0, 0.0, 0.0, 1.0],
        width: 1920,
        height: 1280,
    })
}
