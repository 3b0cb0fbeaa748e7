//! Cost limits checked before the expensive work: the frame's declared image sizes (each and
//! together), its cameras, persons and points, and the pixels its crops may read.

use posefuse_core::error::{Error, Result};

/// Largest image accepted, in pixels (the declared calibration size and the encoded header): the
/// most `--max-image-pixels` may allow.
pub const MAX_IMAGE_PIXELS: u64 = 64 * 1024 * 1024;

/// Checks the declared image size against `max_pixels`.
fn check_declared_size(width: u32, height: u32, max_pixels: u64) -> Result<()> {
    if width > i32::MAX as u32 || height > i32::MAX as u32 {
        return Err(Error::field("calibration.width/height", format!("{width}x{height} exceeds the int32 range")));
    }
    let pixels = width as u64 * height as u64;
    if pixels > max_pixels {
        return Err(Error::field(
            "calibration.width/height",
            format!("{width}x{height} is {pixels} pixels; at most {max_pixels}"),
        ));
    }
    Ok(())
}

/// Cameras per frame (`cameras`). Each one a person uses is decoded, so with
/// [`MAX_FRAME_PIXELS`] this bounds a frame's decoding.
pub const MAX_CAMERAS: usize = 8;

/// Declared pixels of all of a frame's cameras together: one image's limit, so that a frame of
/// several cameras decodes no more than the largest single image may (they are decoded one after
/// the other, but their crops are cut and held together).
pub const MAX_FRAME_PIXELS: u64 = MAX_IMAGE_PIXELS;

/// Per-frame limits on persons, LiDAR points and image size (flags of `posefuse serve`). Each
/// person scans every point of its frame, so their product bounds a frame's point work; an image
/// is decoded one camera at a time, so `max_image_pixels` bounds the memory of a decode.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameLimits {
    pub max_persons: usize,
    pub max_points: usize,
    /// Pixels of one camera image at most (its declared size; its header must match it).
    pub max_image_pixels: u64,
}

impl FrameLimits {
    /// 256 persons; 1,000,000 points (a 32 MiB body holds about 2 million in the base64 form);
    /// images of up to [`MAX_IMAGE_PIXELS`].
    pub const DEFAULT: FrameLimits =
        FrameLimits { max_persons: super::MAX_PERSONS, max_points: 1_000_000, max_image_pixels: MAX_IMAGE_PIXELS };
}

impl Default for FrameLimits {
    fn default() -> Self {
        FrameLimits::DEFAULT
    }
}

impl FrameLimits {
    /// Refuses a frame over a limit, naming the field, before its points are decoded.
    pub fn check(&self, frame: &posefuse_core::frame::Frame) -> Result<()> {
        if frame.cameras.len() > MAX_CAMERAS {
            return Err(Error::field(
                "cameras",
                format!("{} cameras; at most {MAX_CAMERAS} per frame", frame.cameras.len()),
            ));
        }
        if frame.persons.len() > self.max_persons {
            return Err(Error::field(
                "persons",
                format!("{} persons; at most {} per frame", frame.persons.len(), self.max_persons),
            ));
        }
        let points = match &frame.points {
            posefuse_core::frame::Points::Flat(v) => v.len() / 3,
            posefuse_core::frame::Points::Encoded { b64 } => b64.len() / 4 * 3 / 12,
        };
        if points > self.max_points {
            return Err(Error::field("points", format!("{points} points; at most {} per frame", self.max_points)));
        }
        Ok(())
    }

    /// Checks every camera's declared size, and their sum, before anything is decoded.
    pub fn check_declared_sizes(&self, frame: &posefuse_core::frame::Frame) -> Result<()> {
        let mut total = 0u64;
        for (_, at, c) in frame.camera_calibrations() {
            check_declared_size(c.width, c.height, self.max_image_pixels).map_err(|e| e.within(&at))?;
            total += c.width as u64 * c.height as u64;
        }
        if total > MAX_FRAME_PIXELS {
            return Err(Error::field(
                "cameras",
                format!("the cameras' images are {total} pixels together; at most {MAX_FRAME_PIXELS} per frame"),
            ));
        }
        Ok(())
    }
}

/// A frame's crops may read at most this many times the image's pixels in all: a crop's cost
/// grows with its window (side²), so a few huge boxes or many large ones are refused before
/// they are cropped.
pub const CROP_BUDGET_IMAGES: f64 = 32.0;

/// What the crops of one frame may still read.
#[derive(Debug, Clone, Copy)]
pub struct CropBudget {
    left: f64,
    total: f64,
}

impl CropBudget {
    /// The budget of a `width`×`height` frame.
    pub fn for_image(width: u32, height: u32) -> CropBudget {
        let total = CROP_BUDGET_IMAGES * (width as f64 * height as f64).max(1.0);
        CropBudget { left: total, total }
    }

    /// Takes a crop window of `side` pixels from the budget, or refuses the frame naming `field`.
    pub fn spend(&mut self, side: f64, field: &str) -> Result<()> {
        let cost = side * side;
        if cost.is_nan() || cost > self.left {
            return Err(Error::field(
                field,
                format!(
                    "the crops of this frame up to here read {:.0} pixels, more than the limit of {:.0} \
                     ({CROP_BUDGET_IMAGES} times the image): fewer or smaller 2D boxes",
                    self.total - self.left + cost,
                    self.total
                ),
            ));
        }
        self.left -= cost;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crops_share_one_budget_per_frame() {
        let mut b = CropBudget::for_image(100, 100);
        // 32 images of 100x100: 320,000 pixels, e.g. three 300-pixel windows and not a fourth.
        for i in 0..3 {
            b.spend(300.0, &format!("persons[{i}]")).unwrap();
        }
        let e = b.spend(300.0, "persons[3]").unwrap_err();
        assert_eq!(e.field_name(), Some("persons[3]"));
        assert!(CropBudget::for_image(100, 100).spend(f64::NAN, "p").is_err());
    }

    #[test]
    fn declared_sizes_are_bounded() {
        assert!(check_declared_size(1920, 1280, MAX_IMAGE_PIXELS).is_ok());
        assert!(check_declared_size(13_000, 13_000, MAX_IMAGE_PIXELS).is_err());
        assert!(check_declared_size(u32::MAX, 1, MAX_IMAGE_PIXELS).is_err());
        // a lower limit: the camera's own size passes, one pixel more does not
        assert!(check_declared_size(1920, 1280, 1920 * 1280).is_ok());
        assert!(check_declared_size(1921, 1280, 1920 * 1280).is_err());
    }

    fn frame_of_cameras(sizes: &[(u32, u32)]) -> posefuse_core::frame::Frame {
        let cameras: Vec<serde_json::Value> = sizes
            .iter()
            .enumerate()
            .map(|(i, (w, h))| {
                serde_json::json!({"name": format!("c{i}"), "image": "", "calibration": {
                    "intrinsic": [100.0, 100.0, 50.0, 40.0, 0, 0, 0, 0, 0],
                    "extrinsic": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "width": w, "height": h}})
            })
            .collect();
        serde_json::from_value(serde_json::json!({"cameras": cameras, "points": [], "persons": []})).unwrap()
    }

    #[test]
    fn several_cameras_share_one_pixel_limit_and_are_counted() {
        // 5 cameras of 4096x3072 (12.6 Mpx each) fit in 64 Mi pixels, 6 do not
        let limits = FrameLimits::DEFAULT;
        assert!(limits.check_declared_sizes(&frame_of_cameras(&[(4096, 3072); 5])).is_ok());
        // exactly the frame's limit: 4 cameras of 4096x4096 (16 Mi pixels each)
        assert!(limits.check_declared_sizes(&frame_of_cameras(&[(4096, 4096); 4])).is_ok());
        let e = limits.check_declared_sizes(&frame_of_cameras(&[(4096, 3072); 6])).unwrap_err();
        assert_eq!(e.field_name(), Some("cameras"));
        // one camera over the single-image limit is named
        let e = limits.check_declared_sizes(&frame_of_cameras(&[(640, 480), (13_000, 13_000)])).unwrap_err();
        assert_eq!(e.field_name(), Some("cameras[1].calibration.width/height"));
        // the flag's lower limit applies to each camera
        let waymo = FrameLimits { max_image_pixels: 1920 * 1280, ..limits };
        assert!(waymo.check_declared_sizes(&frame_of_cameras(&[(1920, 1280), (1920, 886)])).is_ok());
        let e = waymo.check_declared_sizes(&frame_of_cameras(&[(1920, 1280), (1920, 1281)])).unwrap_err();
        assert_eq!(e.field_name(), Some("cameras[1].calibration.width/height"));
        assert!(limits.check(&frame_of_cameras(&[(64, 48); MAX_CAMERAS])).is_ok());
        let e = limits.check(&frame_of_cameras(&[(64, 48); MAX_CAMERAS + 1])).unwrap_err();
        assert_eq!(e.field_name(), Some("cameras"));
    }
}
