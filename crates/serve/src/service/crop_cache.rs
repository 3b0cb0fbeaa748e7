//! The crops cut from one request's images, kept for the request's later passes (the heading
//! stage plans the frame twice): a crop is a function of its image and window alone
//! (`image_decode::decode_crops`), so a window asked for again is not decoded again, and an
//! image whose pixels would not decode is not tried again.

use image::RgbImage;
use posefuse_core::pipeline::CropTransform;

/// Crops by camera and window, and the cameras whose pixels did not decode (with why).
#[derive(Default)]
pub(super) struct CropCache {
    crops: Vec<(usize, CropTransform, RgbImage)>,
    failed: Vec<(usize, String)>,
    /// Crops cut from the images so far (a hit is not counted).
    pub cut: usize,
}

impl CropCache {
    /// The crop of `window` in camera `camera`, when it was cut before.
    pub fn get(&self, camera: usize, window: &CropTransform) -> Option<&RgbImage> {
        self.crops.iter().find(|(c, w, _)| *c == camera && w == window).map(|(_, _, img)| img)
    }

    /// Keeps a crop just cut.
    pub fn insert(&mut self, camera: usize, window: CropTransform, crop: RgbImage) {
        self.cut += 1;
        self.crops.push((camera, window, crop));
    }

    /// Why camera `camera`'s pixels did not decode, when they did not before.
    pub fn failure(&self, camera: usize) -> Option<&str> {
        self.failed.iter().find(|(c, _)| *c == camera).map(|(_, why)| why.as_str())
    }

    /// Remembers that camera `camera`'s pixels do not decode.
    pub fn fail(&mut self, camera: usize, why: String) {
        self.failed.push((camera, why));
    }
}
