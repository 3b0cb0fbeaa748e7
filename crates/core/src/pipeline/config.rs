//! Pre-processing parameters. They travel with the data: the simulator writes them next to the
//! shards (`dataset.json`), the trainer copies them into the bundle's `manifest.json`
//! (`preprocessing`), and the server reads them from there. Nothing here is hard-coded elsewhere.

use serde::{Deserialize, Serialize};

/// Where the point networks' coordinates come from (docs/BUNDLE.md, "Point frame"). Every frame
/// has its origin at the 3D box's centre and z up; they differ in where x points.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum PointFrame {
    /// x along the box heading: the networks read the body's facing from the box.
    BoxHeading,
    /// x along the horizontal ray from `view_origin` to the box centre: needs no heading, and the
    /// sensor always sits on the −x side, so only the facing relative to the viewer is unknown.
    View,
    /// The vehicle's axes, only translated.
    Centred,
}

/// How a LiDAR point reads the smoothed heatmaps at its projection (docs/BUNDLE.md, "Sampling").
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Sampling {
    /// The cell the point falls in (the paper).
    #[default]
    Nearest,
    /// Between the four cells around the point, weighted by its distance to their centres: a
    /// point between two cells gets evidence from both.
    Bilinear,
}

fn is_nearest(s: &Sampling) -> bool {
    *s == Sampling::Nearest
}

/// The top LiDAR's nominal position in the vehicle frame, from where the view frame's ray starts.
pub const NOMINAL_LIDAR_ORIGIN: [f64; 3] = [1.43, 0.0, 2.12];

fn nominal_lidar_origin() -> [f64; 3] {
    NOMINAL_LIDAR_ORIGIN
}

fn is_nominal_lidar_origin(o: &[f64; 3]) -> bool {
    *o == NOMINAL_LIDAR_ORIGIN
}

/// Every size, constant and switch of the pre-processing pipeline.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PipelineConfig {
    /// Side S of the square camera crop fed to the camera network.
    pub image_size: u32,
    /// The 2D box is grown by this factor (on its longer side) before it is made square.
    pub crop_scale: f64,
    /// Per-channel mean (RGB, on 0..1 values) subtracted before the camera network.
    pub mean: [f32; 3],
    /// Per-channel standard deviation (RGB, on 0..1 values).
    pub std: [f32; 3],
    /// Side of the camera network's heatmaps (S/4 in the paper; any divisor of S).
    pub heatmap_size: u32,
    /// Gaussian smoothing kernel side (odd) applied to heatmaps before sampling.
    pub smoothing_kernel: u32,
    /// Gaussian smoothing sigma, in heatmap cells.
    pub smoothing_sigma: f32,
    /// How points read the smoothed heatmaps; absent: `nearest`, as bundles before it.
    #[serde(default, skip_serializing_if = "is_nearest")]
    pub sampling: Sampling,
    /// Points fed to the point network.
    pub num_points: u32,
    /// Metres added on every side of the 3D box when collecting its points.
    pub box_margin: f64,
    /// Rotate point coordinates by −heading so they are expressed in the box frame. Bundles older
    /// than `frame` say only this; with `frame` present it must agree (true ⇔ `box_heading`).
    pub rotate_by_heading: bool,
    /// The point networks' frame; absent: `box_heading` or `centred` after `rotate_by_heading`
    /// (the form [`PipelineConfig::in_frame`] writes for them, so their files stay as they were).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame: Option<PointFrame>,
    /// Vehicle-frame start of the view frame's ray (metres); written only when not the nominal one.
    #[serde(default = "nominal_lidar_origin", skip_serializing_if = "is_nominal_lidar_origin")]
    pub view_origin: [f64; 3],
    /// Temperature T of eq. 1 (camera-only lifting and pseudo labels): α ∝ exp(−T·d²) with d the
    /// 2D distance in model-input pixels divided by `image_size`, so T does not depend on S.
    pub lift_temperature: f64,
    /// Fewer in-box points than this: the person falls back to camera-only lifting.
    pub min_points: u32,
}

impl Default for PipelineConfig {
    fn default() -> Self {
        PipelineConfig {
            image_size: 256,
            crop_scale: 1.2,
            mean: [0.485, 0.456, 0.406],
            std: [0.229, 0.224, 0.225],
            heatmap_size: 64,
            smoothing_kernel: 7,
            smoothing_sigma: 3.0,
            sampling: Sampling::Nearest,
            num_points: 256,
            box_margin: 0.15,
            rotate_by_heading: true,
            frame: None,
            view_origin: NOMINAL_LIDAR_ORIGIN,
            lift_temperature: 2000.0,
            min_points: 8,
        }
    }
}

impl PipelineConfig {
    /// The default configuration at another crop size (heatmaps at a quarter of it).
    pub fn with_image_size(image_size: u32) -> Self {
        PipelineConfig { image_size, heatmap_size: image_size / 4, ..Self::default() }
    }

    /// The same configuration with the point networks in `frame`. `frame` is only written for the
    /// view frame: `rotate_by_heading` alone says the other two, as it did before `frame` existed.
    pub fn in_frame(self, frame: PointFrame) -> Self {
        PipelineConfig {
            rotate_by_heading: frame == PointFrame::BoxHeading,
            frame: (frame == PointFrame::View).then_some(frame),
            ..self
        }
    }

    /// The frame the point networks see.
    pub fn point_frame(&self) -> PointFrame {
        match (self.frame, self.rotate_by_heading) {
            (Some(f), _) => f,
            (None, true) => PointFrame::BoxHeading,
            (None, false) => PointFrame::Centred,
        }
    }

    /// Checks internal consistency (used when a bundle or a dataset is loaded).
    pub fn validate(&self) -> Result<(), String> {
        if self.image_size < 8 || self.heatmap_size == 0 || !self.image_size.is_multiple_of(self.heatmap_size) {
            return Err(format!(
                "image_size {} must be a multiple of heatmap_size {}",
                self.image_size, self.heatmap_size
            ));
        }
        if self.smoothing_kernel.is_multiple_of(2) {
            return Err(format!("smoothing_kernel must be odd, got {}", self.smoothing_kernel));
        }
        let positive = |v: f32| v.is_finite() && v > 0.0;
        if self.num_points == 0 || !positive(self.smoothing_sigma) || !self.std.iter().all(|s| positive(*s)) {
            return Err("num_points, smoothing_sigma and std must be positive".into());
        }
        if self.crop_scale.is_nan()
            || self.crop_scale < 1.0
            || self.lift_temperature.is_nan()
            || self.lift_temperature <= 0.0
        {
            return Err("crop_scale must be >= 1 and lift_temperature > 0".into());
        }
        if let Some(f) = self.frame {
            if self.rotate_by_heading != (f == PointFrame::BoxHeading) {
                return Err(format!("rotate_by_heading {} contradicts frame {f:?}", self.rotate_by_heading));
            }
        }
        if !self.view_origin.iter().all(|v| v.is_finite()) {
            return Err("view_origin must be finite".into());
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_inconsistent_setting_is_refused_on_its_own() {
        let ok = PipelineConfig::default();
        assert_eq!(ok.validate(), Ok(()));
        let bad = [
            PipelineConfig { image_size: 4, heatmap_size: 1, ..ok.clone() },
            PipelineConfig { heatmap_size: 0, ..ok.clone() },
            PipelineConfig { heatmap_size: 48, ..ok.clone() },
            PipelineConfig { smoothing_kernel: 6, ..ok.clone() },
            PipelineConfig { num_points: 0, ..ok.clone() },
            PipelineConfig { smoothing_sigma: 0.0, ..ok.clone() },
            PipelineConfig { std: [0.2, 0.0, 0.2], ..ok.clone() },
            PipelineConfig { crop_scale: 0.9, ..ok.clone() },
            PipelineConfig { crop_scale: f64::NAN, ..ok.clone() },
            PipelineConfig { lift_temperature: 0.0, ..ok.clone() },
            PipelineConfig { lift_temperature: f64::NAN, ..ok.clone() },
            PipelineConfig { rotate_by_heading: true, ..ok.clone().in_frame(PointFrame::View) },
            PipelineConfig { rotate_by_heading: false, frame: Some(PointFrame::BoxHeading), ..ok.clone() },
            PipelineConfig { view_origin: [0.0, f64::NAN, 0.0], ..ok.clone() },
        ];
        for (i, cfg) in bad.iter().enumerate() {
            assert!(cfg.validate().is_err(), "case {i} accepted: {cfg:?}");
        }
        for f in [PointFrame::BoxHeading, PointFrame::View, PointFrame::Centred] {
            assert_eq!(ok.clone().in_frame(f).validate(), Ok(()));
            assert_eq!(ok.clone().in_frame(f).point_frame(), f);
        }
    }

    #[test]
    fn bundles_without_a_frame_keep_their_meaning() {
        let mut v =
            serde_json::to_value(PipelineConfig::default().in_frame(PointFrame::BoxHeading)).unwrap_or_default();
        assert!(v.get("frame").is_none() && v.get("view_origin").is_none(), "written as before frames: {v}");
        assert_eq!(PipelineConfig::default().in_frame(PointFrame::BoxHeading), PipelineConfig::default());
        let old: PipelineConfig = serde_json::from_value(v.clone()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(old.point_frame(), PointFrame::BoxHeading);
        assert_eq!(old.view_origin, NOMINAL_LIDAR_ORIGIN);
        v["rotate_by_heading"] = false.into();
        let old: PipelineConfig = serde_json::from_value(v.clone()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(old.point_frame(), PointFrame::Centred);
        v["frame"] = "view".into();
        let new: PipelineConfig = serde_json::from_value(v).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(new.point_frame(), PointFrame::View);
    }

    #[test]
    fn bundles_without_a_sampling_keep_the_nearest_cell() {
        let mut v = serde_json::to_value(PipelineConfig::default()).unwrap_or_default();
        assert!(v.get("sampling").is_none(), "written as before sub-cell sampling: {v}");
        let old: PipelineConfig = serde_json::from_value(v.clone()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(old.sampling, Sampling::Nearest);
        v["sampling"] = "bilinear".into();
        let new: PipelineConfig = serde_json::from_value(v.clone()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(new.sampling, Sampling::Bilinear);
        assert_eq!(serde_json::to_value(&new).unwrap_or_default()["sampling"], "bilinear");
        v["sampling"] = "bicubic".into();
        assert!(serde_json::from_value::<PipelineConfig>(v).is_err());
    }
}
