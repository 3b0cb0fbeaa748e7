//! A frame's cameras in the service: the single camera or each of `cameras`, which one each
//! person uses (the one it names, else `geometry::best_camera`), and each camera's image opened
//! (its header read and checked) only when some person uses it, once however many passes plan
//! the frame. Errors about a camera name its field within `cameras[i]`.

use posefuse_core::error::{Error, Result};
use posefuse_core::frame::{Box3d, CameraCalibration, Frame, Person, RgbPixels};
use posefuse_core::geometry::{best_camera, Camera};
use posefuse_core::image_decode::{self, CameraImage, ImageInput, RawImage, RawImages};

/// One camera's image as the request carried it, moved out of the frame, not yet opened.
#[derive(Default)]
struct ImageSource {
    raw: Option<RawImage>,
    base64: Option<String>,
    pixels: Option<RgbPixels>,
}

/// The cameras of one validated frame; each image is opened when first used.
pub(super) struct FrameCameras {
    /// The single-camera form (every person uses camera 0, whatever it names).
    single: bool,
    pub cameras: Vec<Camera>,
    /// `cameras`' names; `None` for the single-camera form (its responses name no camera).
    pub names: Vec<Option<String>>,
    /// Where errors about each camera are named (`""` or `cameras[i]`).
    at: Vec<String>,
    calibrations: Vec<CameraCalibration>,
    sources: Vec<Option<ImageSource>>,
    /// Opened images (`None`: not opened yet, or never used).
    images: Vec<Option<CameraImage>>,
}

impl FrameCameras {
    /// The cameras of `frame` (validated), their images moved out of it: `raw` holds the images
    /// sent as bytes beside it (camera order).
    pub fn take(frame: &mut Frame, raw: Option<RawImages>) -> Result<Self> {
        let pixels = frame.take_pixels();
        let calibrations: Vec<(Option<String>, String, CameraCalibration)> = frame
            .camera_calibrations()
            .into_iter()
            .map(|(name, at, c)| (name.map(str::to_string), at, c.clone()))
            .collect();
        let n = calibrations.len();
        let single = frame.cameras.is_empty();
        let mut base64: Vec<Option<String>> =
            if single { vec![frame.image.take()] } else { frame.cameras.iter_mut().map(|c| c.image.take()).collect() };
        let mut raw = raw.map(|r| r.0).unwrap_or_default().into_iter();
        let mut pixels = pixels.into_iter();
        let mut out = FrameCameras {
            single,
            cameras: Vec::with_capacity(n),
            names: Vec::with_capacity(n),
            at: Vec::with_capacity(n),
            calibrations: Vec::with_capacity(n),
            sources: Vec::with_capacity(n),
            images: (0..n).map(|_| None).collect(),
        };
        for (i, (name, at, calibration)) in calibrations.into_iter().enumerate() {
            out.cameras.push(Camera::from_calibration(&calibration).map_err(|e| e.within(&at))?);
            let source = ImageSource {
                raw: raw.next(),
                base64: base64.get_mut(i).and_then(Option::take),
                pixels: pixels.next().flatten(),
            };
            if name.is_some() {
                require_one_image(&source, &at)?;
            }
            out.names.push(name);
            out.at.push(at);
            out.calibrations.push(calibration);
            out.sources.push(Some(source));
        }
        Ok(out)
    }

    /// The camera `person` uses with its 3D box at `box_3d`: the one it names, the single
    /// camera, or the one that sees the box best (none when no camera does).
    pub fn choose(&self, person: &Person, box_3d: &Box3d) -> Option<usize> {
        match &person.camera {
            _ if self.single => Some(0),
            Some(name) => self.names.iter().position(|n| n.as_deref() == Some(name.as_str())),
            None => best_camera(&self.cameras, box_3d),
        }
    }

    /// Opens the images of the cameras in `used` that are not open yet (header read and checked,
    /// pixels not decoded); the others stay unopened.
    pub fn open_used(&mut self, used: &[Option<usize>]) -> Result<()> {
        for c in 0..self.cameras.len() {
            if self.images[c].is_some() || !used.contains(&Some(c)) {
                continue;
            }
            let Some(source) = self.sources[c].take() else { continue };
            let (raw, rows) = match source.raw {
                Some(RawImage::Encoded(bytes)) => (Some(bytes), None),
                Some(RawImage::Rows(rows)) => (None, Some(rows)),
                None => (None, None),
            };
            let input = ImageInput { raw, base64: source.base64.as_deref(), pixels: source.pixels, rows };
            let image = image_decode::open_camera(input, &self.calibrations[c]).map_err(|e| e.within(&self.at[c]))?;
            self.images[c] = Some(image);
        }
        Ok(())
    }

    /// Camera `c`'s image once opened ([`FrameCameras::open_used`]); `Absent` before.
    pub fn image(&self, c: usize) -> &CameraImage {
        static ABSENT: CameraImage = CameraImage::Absent;
        self.images.get(c).and_then(Option::as_ref).unwrap_or(&ABSENT)
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
fn require_one_image(source: &ImageSource, at: &str) -> Result<()> {
    let encoded = matches!(&source.raw, Some(RawImage::Encoded(b)) if !b.is_empty()) || source.base64.is_some();
    let pixels = source.pixels.is_some() || matches!(source.raw, Some(RawImage::Rows(_)));
    match (encoded, pixels) {
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
