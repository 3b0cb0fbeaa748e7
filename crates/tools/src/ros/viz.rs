//! Poses as Foxglove's published schemas: a `foxglove.SceneUpdate` of 3D skeletons (one entity
//! per person id, spheres at the keypoints and a line list along the bones, in the boxes' frame)
//! and a `foxglove.ImageAnnotations` of 2D skeletons per camera, stamped as its image.

use foxglove::schemas::{
    line_primitive, points_annotation, scene_entity_deletion, CircleAnnotation, Color, ImageAnnotations, KeyValuePair,
    LinePrimitive, Point2, Point3, PointsAnnotation, Pose, Quaternion, SceneEntity, SceneEntityDeletion, SceneUpdate,
    SpherePrimitive, Timestamp, Vector3,
};

use posefuse_core::keypoints::{NAMES, SKELETON};
use posefuse_serve::service::api::PersonPose;

/// Keypoint sphere diameter, metres.
const SPHERE_M: f64 = 0.06;
const LINE_M: f64 = 0.02;

/// A stamp in Foxglove's unsigned form (stamps before 1970 become 0).
pub fn timestamp(ns: i64) -> Timestamp {
    let ns = ns.max(0);
    Timestamp::new((ns / 1_000_000_000).min(u32::MAX as i64) as u32, (ns % 1_000_000_000) as u32)
}

/// Left side blue, right side red, the nose white, as most pose viewers colour them.
fn side_color(keypoint: usize) -> Color {
    let name = NAMES[keypoint];
    let (r, g, b) = if name.starts_with("left") {
        (0.2, 0.5, 1.0)
    } else if name.starts_with("right") {
        (1.0, 0.3, 0.2)
    } else {
        (1.0, 1.0, 1.0)
    };
    Color { r, g, b, a: 1.0 }
}

const BONE: Color = Color { r: 0.1, g: 0.9, b: 0.4, a: 1.0 };

/// The 3D skeletons of one frame; every entity of the previous frame is deleted first.
pub fn scene_update(stamp_ns: i64, frame_id: &str, persons: &[PersonPose]) -> SceneUpdate {
    let ts = Some(timestamp(stamp_ns));
    let entities = persons
        .iter()
        .map(|p| {
            let at = |k: usize| {
                let [x, y, z] = p.keypoints[k].xyz;
                Point3 { x, y, z }
            };
            SceneEntity {
                timestamp: ts,
                frame_id: frame_id.to_owned(),
                id: p.id.clone(),
                metadata: vec![KeyValuePair { key: "mode".into(), value: p.mode.as_str().into() }],
                spheres: (0..p.keypoints.len().min(NAMES.len()))
                    .map(|k| {
                        let Point3 { x, y, z } = at(k);
                        SpherePrimitive {
                            pose: Some(Pose {
                                position: Some(Vector3 { x, y, z }),
                                orientation: Some(Quaternion { x: 0.0, y: 0.0, z: 0.0, w: 1.0 }),
                            }),
                            size: Some(Vector3 { x: SPHERE_M, y: SPHERE_M, z: SPHERE_M }),
                            color: Some(side_color(k)),
                        }
                    })
                    .collect(),
                lines: vec![LinePrimitive {
                    r#type: line_primitive::Type::LineList as i32,
                    pose: Some(Pose {
                        position: Some(Vector3 { x: 0.0, y: 0.0, z: 0.0 }),
                        orientation: Some(Quaternion { x: 0.0, y: 0.0, z: 0.0, w: 1.0 }),
                    }),
                    thickness: LINE_M,
                    scale_invariant: false,
                    points: SKELETON
                        .iter()
                        .filter(|(a, b)| *a < p.keypoints.len() && *b < p.keypoints.len())
                        .flat_map(|&(a, b)| [at(a), at(b)])
                        .collect(),
                    color: Some(BONE),
                    ..Default::default()
                }],
                ..Default::default()
            }
        })
        .collect();
    SceneUpdate {
        deletions: vec![SceneEntityDeletion {
            timestamp: ts,
            r#type: scene_entity_deletion::Type::All as i32,
            id: String::new(),
        }],
        entities,
    }
}

/// The 2D skeletons of the persons seen by one camera (`camera` as in the response), at the
/// image's stamp: a circle per keypoint with pixels, a line list along the bones.
pub fn image_annotations(image_stamp_ns: i64, camera: &str, persons: &[PersonPose]) -> ImageAnnotations {
    let ts = Some(timestamp(image_stamp_ns));
    let mine = persons.iter().filter(|p| p.camera.as_deref() == Some(camera));
    let mut out = ImageAnnotations::default();
    for p in mine {
        let uv = |k: usize| p.keypoints.get(k).and_then(|kp| kp.uv).map(|[x, y]| Point2 { x, y });
        out.circles.extend((0..p.keypoints.len().min(NAMES.len())).filter_map(|k| {
            uv(k).map(|position| CircleAnnotation {
                timestamp: ts,
                position: Some(position),
                diameter: 6.0,
                thickness: 1.0,
                fill_color: Some(side_color(k)),
                outline_color: Some(side_color(k)),
                ..Default::default()
            })
        }));
        let bones: Vec<Point2> = SKELETON.iter().filter_map(|&(a, b)| Some([uv(a)?, uv(b)?])).flatten().collect();
        if !bones.is_empty() {
            out.points.push(PointsAnnotation {
                timestamp: ts,
                r#type: points_annotation::Type::LineList as i32,
                points: bones,
                outline_color: Some(BONE),
                thickness: 2.0,
                ..Default::default()
            });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use posefuse_core::keypoints::{K, WAYMO_TYPES};
    use posefuse_serve::service::api::{KeypointPose, Mode};

    fn person(id: &str, camera: Option<&str>, with_uv: bool) -> PersonPose {
        PersonPose {
            id: id.into(),
            camera: camera.map(str::to_owned),
            mode: Mode::Fusion,
            mode_reason: String::new(),
            num_points: 10,
            box_2d: None,
            keypoints: (0..K)
                .map(|k| KeypointPose {
                    name: NAMES[k].into(),
                    waymo_type: WAYMO_TYPES[k],
                    xyz: [k as f64, 0.0, 1.0],
                    uv: (with_uv && k != 5).then_some([10.0 * k as f64, 20.0]),
                    score: None,
                })
                .collect(),
            facing: None,
        }
    }

    #[test]
    fn a_scene_update_clears_the_last_frame_and_draws_each_person() {
        let u = scene_update(1_500_000_000, "base_link", &[person("a", None, false), person("b", None, false)]);
        assert_eq!(u.deletions.len(), 1);
        assert_eq!(u.deletions[0].r#type, scene_entity_deletion::Type::All as i32);
        assert_eq!(u.entities.iter().map(|e| e.id.as_str()).collect::<Vec<_>>(), ["a", "b"]);
        let e = &u.entities[0];
        assert_eq!(e.frame_id, "base_link");
        assert_eq!(e.timestamp, Some(Timestamp::new(1, 500_000_000)));
        assert_eq!(e.spheres.len(), K);
        assert_eq!(e.spheres[4].pose.unwrap().position.unwrap().x, 4.0);
        assert_eq!(e.lines[0].points.len(), 2 * SKELETON.len());
        // the first bone joins the shoulders
        assert_eq!((e.lines[0].points[0].x, e.lines[0].points[1].x), (1.0, 2.0));
        assert_eq!(e.spheres[1].color, Some(side_color(1)));
        assert_ne!(side_color(1), side_color(2));
    }

    #[test]
    fn annotations_carry_only_the_cameras_persons_and_bones_with_both_ends() {
        let ps = [person("a", Some("/front"), true), person("b", Some("/side"), true), person("c", None, false)];
        let a = image_annotations(7, "/front", &ps);
        assert_eq!(a.circles.len(), K - 1);
        // keypoint 5 (left elbow) has no pixel: its two bones are left out
        let bones_without_5 = SKELETON.iter().filter(|(x, y)| *x != 5 && *y != 5).count();
        assert_eq!(a.points.len(), 1);
        assert_eq!(a.points[0].points.len(), 2 * bones_without_5);
        assert_eq!(a.points[0].timestamp, Some(timestamp(7)));
        assert!(image_annotations(7, "/rear", &ps).circles.is_empty());
    }

    #[test]
    fn stamps_before_1970_are_clamped() {
        assert_eq!(timestamp(-5), Timestamp::new(0, 0));
        assert_eq!(timestamp(3_000_000_001), Timestamp::new(3, 1));
    }
}
