//! Which model path answers a person: the service's mode policy, a pure function so that every
//! branch is tested on its own (the paper's three estimators; docs/ARCHITECTURE.md).

use super::api::Mode;
use posefuse_core::error::{Error, Result};
use posefuse_core::frame::RequestedMode;

/// The mode that runs for a person and why. `camera_problem` is `(field, why)` when the camera
/// cannot serve this person (no image, undecodable, outside the view). In `auto`, fusion needs
/// the camera and at least `min_points` points in the box; with fewer points the camera's
/// keypoints are lifted onto them (camera mode); without a usable camera the LiDAR network runs.
/// A forced camera-needing mode without a usable camera is the request's error.
pub fn choose_mode(
    requested: RequestedMode,
    camera_problem: Option<(String, String)>,
    num_points: usize,
    min_points: usize,
) -> Result<(Mode, String)> {
    Ok(match (requested, camera_problem) {
        (RequestedMode::Auto, None) if num_points >= min_points => {
            (Mode::Fusion, format!("camera and LiDAR usable ({num_points} points in the box)"))
        }
        (RequestedMode::Auto, None) => (
            Mode::Camera,
            format!("only {num_points} points in the box (fewer than {min_points}): camera keypoints lifted onto them"),
        ),
        (RequestedMode::Auto, Some((_, why))) => (Mode::Lidar, format!("camera unusable: {why}")),
        (RequestedMode::Lidar, _) => (Mode::Lidar, "requested".into()),
        (RequestedMode::Fusion | RequestedMode::Camera, Some((field, why))) => {
            return Err(Error::field(field, format!("mode {requested:?} needs the camera: {why}")));
        }
        (RequestedMode::Fusion, None) => (Mode::Fusion, "requested".into()),
        (RequestedMode::Camera, None) => (Mode::Camera, "requested".into()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mode(requested: RequestedMode, problem: bool, points: usize) -> Result<Mode> {
        let problem = problem.then(|| ("image".to_string(), "no image in the request".to_string()));
        choose_mode(requested, problem, points, 20).map(|(m, _)| m)
    }

    #[test]
    fn auto_takes_fusion_from_min_points_on_and_camera_below() {
        assert_eq!(mode(RequestedMode::Auto, false, 20).unwrap(), Mode::Fusion);
        assert_eq!(mode(RequestedMode::Auto, false, 21).unwrap(), Mode::Fusion);
        assert_eq!(mode(RequestedMode::Auto, false, 19).unwrap(), Mode::Camera);
        assert_eq!(mode(RequestedMode::Auto, false, 1).unwrap(), Mode::Camera);
    }

    #[test]
    fn auto_without_a_camera_is_lidar_whatever_the_points() {
        assert_eq!(mode(RequestedMode::Auto, true, 500).unwrap(), Mode::Lidar);
        assert_eq!(mode(RequestedMode::Auto, true, 3).unwrap(), Mode::Lidar);
    }

    #[test]
    fn forced_modes_run_as_asked_or_name_the_missing_camera() {
        assert_eq!(mode(RequestedMode::Lidar, false, 500).unwrap(), Mode::Lidar);
        assert_eq!(mode(RequestedMode::Lidar, true, 5).unwrap(), Mode::Lidar);
        assert_eq!(mode(RequestedMode::Fusion, false, 5).unwrap(), Mode::Fusion);
        assert_eq!(mode(RequestedMode::Camera, false, 500).unwrap(), Mode::Camera);
        for forced in [RequestedMode::Fusion, RequestedMode::Camera] {
            let e = mode(forced, true, 500).unwrap_err();
            assert_eq!(e.field_name(), Some("image"));
            assert!(e.to_string().contains("needs the camera"), "{e}");
        }
    }

    #[test]
    fn the_reason_says_why() {
        let (_, why) = choose_mode(RequestedMode::Auto, None, 7, 20).unwrap();
        assert!(why.contains("only 7 points") && why.contains("fewer than 20"), "{why}");
        let (_, why) = choose_mode(RequestedMode::Auto, None, 30, 20).unwrap();
        assert!(why.contains("30 points"), "{why}");
        let problem = Some(("image".to_string(), "undecodable".to_string()));
        let (_, why) = choose_mode(RequestedMode::Auto, problem, 30, 20).unwrap();
        assert_eq!(why, "camera unusable: undecodable");
    }
}
