//! Pure pre- and post-processing: no I/O, no model. One implementation, used by the server on
//! every request and by the simulator to write training data.

mod config;
mod crop;
mod decode_plan;
mod facing;
mod fusion;
mod lift;
mod points;
mod prepare;

pub use config::{PipelineConfig, PointFrame, Sampling, NOMINAL_LIDAR_ORIGIN};
pub use crop::{crop_rgb, normalize, CropTransform};
pub use decode_plan::{
    pixel_region, plan_decode, plan_passes, scaled, window_denominator, DecodePass, DecodePlan, PixelRect,
    CROP_DENOMINATORS, DCT_DENOMINATORS,
};
pub use facing::{facing, yaw_difference, Facing, FULL_WIDTH_M};
pub use fusion::{
    bilinear_cell, cell_index, fused_points, fusion_features, fusion_input, gaussian_kernel, lidar_points,
    sample_bilinear, sample_features, smooth_heatmaps, smoothed_features,
};
pub use lift::{decode_heatmaps, lift, reliability};
pub use points::{
    from_local, gather_points, input_seed, model_frame, model_uv, point_input, select_indices, to_local, turn_points,
    PersonPoints, PointInput,
};
pub use prepare::{keypoints_to_vehicle, prepare_person, PreparedPerson};
