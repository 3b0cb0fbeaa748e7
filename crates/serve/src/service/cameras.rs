//! A frame's cameras in the service: the single camera or each of `cameras`, which one each
//! person uses (the one it names, else `geometry::best_camera`), and each camera's image opened
//! only when some person uses it. Errors about a camera name its field within `cameras[i]`.

use posefuse_core::error::{Error, Result};
use posefuse_core::frame::{CameraCalibration, Frame, Person, RgbPixels};
use posefuse_core::geometry::{best_camera, Camera};
use posefuse_core::image_decode::{self, CameraImage, ImageInput, RawImages};

/// The cameras of one frame, their images not yet opened.
pub(super) struct FrameCameras<'f> {
    frame: &'f Frame,
    pub cameras: Vec<Camera>,
    /// `cameras`' names; `None` for the single-camera form (its responses name no camera).
    pub names: Vec<Option<String>>,
    /// Where errors about each camera are named (`""` or `cameras[i]`).
    at: Vec<String>,
    calibrations: Vec<&'f CameraCalibration>,
    inputs: Vec<Option<ImageInput<'f>>>,
}

impl<'f> FrameCameras<'f> {
    /// The validated frame's cameras: `raw` holds the images sent as bytes beside it (camera
    /// order), `pixels` those moved out of it (`Frame::take_pixels`).
    pub fn new(frame: &'f Frame, raw: Option<RawImages>, pixels: Vec<Option<RgbPixels>>) -> Result<Self> {
        let calibrations = frame.camera_calibrations();
        let n = calibrations.len();
        let mut raw = raw.map(|r| r.0).unwrap_or_default().into_iter();
        let mut pixels = pixels.into_iter();
        let mut out = FrameCameras {
            frame,
            cameras: Vec::with_capacity(n),
            names: Vec::with_capacity(n),
            at: Vec::with_capacity(n),
            calibrations: Vec::with_capacity(n),
            inputs: Vec::with_capacity(n),
        };
        for (i, (name, at, calibration)) in calibrations.into_iter().enumerate() {
            out.cameras.push(Camera::from_calibration(calibration).map_err(|e| e.within(&at))?);
            let base64 = match name {
                None => frame.image.as_deref(),
                Some(_) => frame.cameras.get(i).and_then(|c| c.image.as_deref()),
            };
            let input = ImageInput { raw: raw.next(), base64, pixels: pixels.next().flatten() };
            if name.is_some() {
                require_one_image(&input, &at)?;
            }
            out.names.push(name.map(str::to_string));
            out.at.push(at);
            out.calibrations.push(calibration);
            out.inputs.push(Some(input));
        }
        Ok(out)
    }

    /// The camera `person` uses: the one it names, the single camera, or the one that sees its
    /// 3D box best (none when no camera does).
    pub fn choose(&self, person: &Person) -> Option<usize> {
        match &person.camera {
            _ if self.frame.cameras.is_empty() => Some(0),
            Some(name) => self.names.iter().position(|n| n.as_deref() == Some(name.as_str())),
            None => best_camera(&self.cameras, &person.box_3d),
        }
    }

    /// The images of the cameras in `used` (header read and checked, pixels not decoded); the
    /// others stay unopened (`Absent`, never consulted).
    pub fn open_used(&mut self, used: &[Option<usize>]) -> Result<Vec<CameraImage>> {
        let mut images = Vec::with_capacity(self.cameras.len());
        for (c, input) in self.inputs.iter_mut().enumerate() {
            let image = match input.take() {
                Some(input) if used.contains(&Some(c)) => {
                    image_decode::open_camera(input, self.calibrations[c]).map_err(|e| e.within(&self.at[c]))?
                }
                _ => CameraImage::Absent,
            };
            images.push(image);
        }
        Ok(images)
    }

    /// A field of camera `c` (`image` or `cameras[c].image`).
    pub fn field(&self, c: usize, name: &str) -> String {
        match self.at[c].as_str() {
            "" => name.to_string(),
            at => format!("{at}.{name}"),
        }
    }
}

/// Each of `cameras` sends exactly one of an encoded image and pixels.
fn require_one_image(input: &ImageInput<'_>, at: &str) -> Result<()> {
    let encoded = input.raw.as_ref().is_some_and(|b| !b.is_empty()) || input.base64.is_some();
    match (encoded, input.pixels.is_some()) {
        (true, true) => {
            Err(Error::field(format!("{at}.image_rgb"), "send either an encoded image or image_rgb pixels, not both"))
        }
        (false, false) => Err(Error::field(
            format!("{at}.image"),
            "required: each of `cameras` sends its image (JPEG/PNG) or image_rgb pixels",
        )),
        _ => Ok(()),
    }
}
