//! Sensor geometry with Waymo's conventions: camera model with OpenCV distortion, 3D and 2D boxes.

mod boxes;
mod camera;
mod camera_choice;
mod image_boxes;
mod nominal;
pub mod rigid;

pub use boxes::{box2d_contains, box2d_from_points, BoxFrame};
pub use camera::{Camera, Projection, RADIAL_FACTOR_RANGE};
pub use camera_choice::{best_camera, visible_share, VisibleShare};
pub use image_boxes::{clip_to_image, overlaps_image, projected_box};
pub use nominal::nominal_camera;
