//! The multi-camera form of a frame (`cameras`): its type, the checks that a frame uses exactly
//! one form with distinct named cameras, and the persons' cameras by name.

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::frame::{CameraCalibration, Frame, Person, RgbPixels};

/// One camera of a multi-camera frame: the same fields as the single-camera form, with a name.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FrameCamera {
    /// Unique among the frame's cameras (e.g. `FRONT`); persons and responses name it.
    pub name: String,
    /// Base64 of a JPEG or PNG file; each camera sends `image` or `image_rgb`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image: Option<String>,
    /// Decoded pixels instead of `image` (never both).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image_rgb: Option<RgbPixels>,
    /// Calibration of this camera.
    pub calibration: CameraCalibration,
}

impl Frame {
    /// The frame's cameras in order: the single camera (unnamed) or each of `cameras`, with the
    /// field path errors about it are named under (`""` or `cameras[i]`).
    pub fn camera_calibrations(&self) -> Vec<(Option<&str>, String, &CameraCalibration)> {
        match &self.calibration {
            Some(c) if self.cameras.is_empty() => vec![(None, String::new(), c)],
            _ => self
                .cameras
                .iter()
                .enumerate()
                .map(|(i, c)| (Some(c.name.as_str()), format!("cameras[{i}]"), &c.calibration))
                .collect(),
        }
    }

    /// The calibration a person named `camera` refers to: the single camera's whatever the
    /// name, else the named one of `cameras`.
    pub fn calibration_of(&self, camera: Option<&str>) -> Option<&CameraCalibration> {
        if self.cameras.is_empty() {
            return self.calibration.as_ref();
        }
        let name = camera?;
        self.cameras.iter().find(|c| c.name == name).map(|c| &c.calibration)
    }

    /// The decoded pixels of every camera, in camera order, moved out of the frame so that they
    /// are not copied.
    pub fn take_pixels(&mut self) -> Vec<Option<RgbPixels>> {
        if self.cameras.is_empty() {
            vec![self.image_rgb.take()]
        } else {
            self.cameras.iter_mut().map(|c| c.image_rgb.take()).collect()
        }
    }

    /// One form or the other; named, distinct, valid cameras.
    pub(crate) fn validate_cameras(&self) -> Result<()> {
        if self.cameras.is_empty() {
            return match &self.calibration {
                Some(c) => c.validate(),
                None => Err(Error::field("calibration", "required (or `cameras`, one entry per camera)")),
            };
        }
        let single = [
            ("calibration", self.calibration.is_some()),
            ("image", self.image.is_some()),
            ("image_rgb", self.image_rgb.is_some()),
        ];
        if let Some((name, _)) = single.iter().find(|(_, given)| *given) {
            return Err(Error::field(
                "cameras",
                format!(
                    "given together with the single-camera `{name}`: send every camera inside `cameras`, \
                     or one camera without `cameras`"
                ),
            ));
        }
        let mut names = std::collections::HashSet::new();
        for (i, c) in self.cameras.iter().enumerate() {
            let at = format!("cameras[{i}]");
            if c.name.trim().is_empty() {
                return Err(Error::field(format!("{at}.name"), "must not be empty"));
            }
            if !names.insert(c.name.as_str()) {
                return Err(Error::field(format!("{at}.name"), format!("duplicate camera name `{}`", c.name)));
            }
            // whether it sends one image is checked where the bytes gRPC sends beside it are known
            c.calibration.validate().map_err(|e| e.within(&at))?;
        }
        Ok(())
    }

    /// A person's `camera` names one of `cameras`; a `box_2d` says which camera's pixels it is in.
    pub(crate) fn validate_person_camera(&self, p: &Person, field: &str) -> Result<()> {
        match &p.camera {
            Some(_) if self.cameras.is_empty() => {
                Err(Error::field(format!("{field}.camera"), "the frame has no `cameras` to choose from"))
            }
            Some(name) if !self.cameras.iter().any(|c| &c.name == name) => Err(Error::field(
                format!("{field}.camera"),
                format!("no camera named `{name}` in `cameras` (names: {})", self.camera_names()),
            )),
            None if p.box_2d.is_some() && !self.cameras.is_empty() => Err(Error::field(
                format!("{field}.camera"),
                "required with `box_2d` when the frame has `cameras`: the box is in one camera's pixels",
            )),
            _ => Ok(()),
        }
    }

    fn camera_names(&self) -> String {
        self.cameras.iter().map(|c| format!("`{}`", c.name)).collect::<Vec<_>>().join(", ")
    }
}

#[cfg(test)]
mod tests {
    use crate::error::Error;
    use crate::frame::Frame;

    fn two_camera_frame() -> serde_json::Value {
        let calib = serde_json::json!({"intrinsic": [100.0, 100.0, 50.0, 40.0, 0, 0, 0, 0, 0],
            "extrinsic": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "width": 100, "height": 80});
        serde_json::json!({
            "cameras": [
                {"name": "front", "image": "AAAA", "calibration": calib},
                {"name": "side", "image": "AAAA", "calibration": calib},
            ],
            "points": [10.0, 0.0, 1.0],
            "persons": [{"id": "p", "camera": "side",
                "box_3d": {"center_x": 10.0, "center_y": 0.0, "center_z": 1.0,
                           "length": 0.6, "width": 0.6, "height": 1.8, "heading": 0.0}}]
        })
    }

    fn field_of(v: serde_json::Value) -> String {
        let f: Frame = serde_json::from_value(v).unwrap();
        match f.validate() {
            Err(Error::InvalidField { field, .. }) => field,
            other => panic!("expected an invalid-field error, got {other:?}"),
        }
    }

    #[test]
    fn a_two_camera_frame_is_valid_and_round_trips() {
        let f: Frame = serde_json::from_value(two_camera_frame()).unwrap();
        f.validate().unwrap();
        let back: Frame = serde_json::from_str(&serde_json::to_string(&f).unwrap()).unwrap();
        assert_eq!(back, f);
        assert_eq!(f.calibration_of(Some("side")).map(|c| c.width), Some(100));
        assert_eq!(f.calibration_of(Some("rear")), None);
        assert_eq!(f.calibration_of(None), None);
        let names: Vec<_> = f.camera_calibrations().into_iter().map(|(n, at, _)| (n, at)).collect();
        assert_eq!(names, [(Some("front"), "cameras[0]".to_string()), (Some("side"), "cameras[1]".to_string())]);
    }

    #[test]
    fn each_camera_error_names_its_field() {
        let mut v = two_camera_frame();
        v["calibration"] = v["cameras"][0]["calibration"].clone();
        assert_eq!(field_of(v), "cameras");
        let mut v = two_camera_frame();
        v["image"] = "AAAA".into();
        assert_eq!(field_of(v), "cameras");
        let mut v = two_camera_frame();
        v["cameras"][1]["name"] = "front".into();
        assert_eq!(field_of(v), "cameras[1].name");
        let mut v = two_camera_frame();
        v["cameras"][0]["name"] = " ".into();
        assert_eq!(field_of(v), "cameras[0].name");
        let mut v = two_camera_frame();
        v["cameras"][1]["calibration"]["intrinsic"][0] = 0.0.into();
        assert_eq!(field_of(v), "cameras[1].calibration.intrinsic[0] (f_u)");
        let mut v = two_camera_frame();
        v["persons"][0]["camera"] = "rear".into();
        assert_eq!(field_of(v), "persons[0].camera");
        let mut v = two_camera_frame();
        v["persons"][0].as_object_mut().unwrap().remove("camera");
        v["persons"][0]["box_2d"] = serde_json::json!({"center_x": 50, "center_y": 40, "width": 10, "height": 20});
        assert_eq!(field_of(v), "persons[0].camera");
        let mut v = two_camera_frame();
        v.as_object_mut().unwrap().remove("cameras");
        assert_eq!(field_of(v), "calibration");
    }

    #[test]
    fn a_single_camera_frame_cannot_name_a_camera() {
        let mut v = two_camera_frame();
        v["calibration"] = v["cameras"][0]["calibration"].clone();
        v.as_object_mut().unwrap().remove("cameras");
        assert_eq!(field_of(v.clone()), "persons[0].camera");
        v["persons"][0].as_object_mut().unwrap().remove("camera");
        let f: Frame = serde_json::from_value(v).unwrap();
        f.validate().unwrap();
        assert_eq!(f.calibration_of(Some("anything")).map(|c| c.height), Some(80));
    }
}
