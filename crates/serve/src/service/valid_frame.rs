//! One validation pass: a parsed [`Frame`] becomes a [`ValidFrame`] once, before any pixel is
//! decoded: the per-frame limits (cameras, persons, points), the fields (boxes, ids, cameras,
//! calibrations), the declared image sizes, each camera's image given in exactly one form, and
//! the points decoded and present. Planning, the heading stage and inference trust it and check
//! none of this again. What can only be known later (an image's header, a box against its
//! image, the crops' budget) is checked where it is first known (`plan`).

use posefuse_core::error::{Error, Result};
use posefuse_core::frame::{Box3d, Frame, Person, RequestedMode};
use posefuse_core::image_decode::RawImages;

use super::cameras::FrameCameras;
use super::limits::FrameLimits;

/// A frame that passed [`ValidFrame::new`]: its points decoded, its images moved out of it and
/// opened only when a person uses them.
pub(super) struct ValidFrame {
    pub frame_id: Option<String>,
    pub mode: RequestedMode,
    pub persons: Vec<Person>,
    pub points: Vec<[f32; 3]>,
    pub cameras: FrameCameras,
}

impl ValidFrame {
    /// Checks `frame` once (in the order above: the cheapest refusals first); `raw` holds the
    /// images sent as bytes beside it (gRPC, KServe), in camera order.
    pub fn new(mut frame: Frame, raw: Option<RawImages>, limits: &FrameLimits) -> Result<ValidFrame> {
        limits.check(&frame)?;
        frame.validate()?;
        limits.check_declared_sizes(&frame)?;
        let cameras = FrameCameras::take(&mut frame, raw)?;
        let points = frame.points.decode()?;
        if points.is_empty() {
            return Err(Error::field("points", "no LiDAR points: every mode needs the points of the persons' boxes"));
        }
        Ok(ValidFrame { frame_id: frame.frame_id, mode: frame.mode, persons: frame.persons, points, cameras })
    }

    /// The persons' 3D boxes as given.
    pub fn boxes(&self) -> Vec<Box3d> {
        self.persons.iter().map(|p| p.box_3d).collect()
    }
}
