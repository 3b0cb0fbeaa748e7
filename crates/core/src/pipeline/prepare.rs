//! One person of a frame, prepared for the networks: the composition the server runs on every
//! request and the simulator runs to write training shards.

use image::RgbImage;

use super::{
    crop_rgb, from_local, gather_points, point_input, CropTransform, PersonPoints, PipelineConfig, PointInput,
};
use crate::frame::{Box2d, Box3d};
use crate::geometry::{BoxFrame, Camera};

/// What the pipeline made of one person.
#[derive(Debug, Clone)]
pub struct PreparedPerson {
    pub box_frame: BoxFrame,
    /// Crop transform, when there is a 2D box to crop around.
    pub crop: Option<CropTransform>,
    /// The S×S RGB crop (before normalization), when there is an image and a 2D box.
    pub crop_rgb: Option<RgbImage>,
    /// All points in the 3D box.
    pub points: PersonPoints,
    /// The network's N points, `None` when the box holds no points.
    pub input: Option<PointInput>,
}

/// Prepares one person. `image` is the frame's decoded image (decode once per frame); without
/// `box2d` there is no crop and the points carry no projections.
pub fn prepare_person(
    image: Option<&RgbImage>,
    camera: Option<&Camera>,
    points: &[[f32; 3]],
    box3d: &Box3d,
    box2d: Option<&Box2d>,
    cfg: &PipelineConfig,
) -> PreparedPerson {
    let box_frame = BoxFrame::new(box3d);
    let crop = box2d.map(|b| CropTransform::for_box(b, cfg));
    let crop_img = match (image, crop.as_ref()) {
        (Some(img), Some(t)) => Some(crop_rgb(img, t)),
        _ => None,
    };
    let pts = gather_points(points, &box_frame, cfg);
    let input = point_input(&pts, camera, crop.as_ref(), cfg);
    PreparedPerson { box_frame, crop, crop_rgb: crop_img, points: pts, input }
}

/// Keypoints from the network (model-input coordinates) in the vehicle frame.
pub fn keypoints_to_vehicle(local: &[[f32; 3]], b: &BoxFrame, cfg: &PipelineConfig) -> Vec<[f64; 3]> {
    local.iter().map(|q| from_local(b, [q[0] as f64, q[1] as f64, q[2] as f64], cfg)).collect()
}
