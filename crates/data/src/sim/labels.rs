//! Labels of a placed person: exact and annotator-noisy 2D keypoints, camera visibility by ray
//! test, the 2D box, and 3D visibility.
//!
//! What is labelled, as Waymo's annotators label (docs/DATA.md): a person with at least one visible
//! keypoint gets every 3D keypoint labelled, and every 2D keypoint that projects into the image
//! (2D only when the camera sees one of them); a labelled keypoint that is not visible is marked
//! occluded, and counts in the metrics all the same. A person nothing of whose joints is seen gets
//! no keypoint labels, as annotators leave them.
//!
//! Occlusion rule: keypoint k is visible in the camera when it projects inside the image and the
//! first surface hit along the camera ray toward it belongs to the same person, on one of the
//! body parts that meet at that joint (`body::keypoint_parts`), no farther than the body's
//! thickness there plus 6 cm from the keypoint (`Skeleton::visibility_tolerance`). Anything else
//! in front — another object, the ground, or the person's own other limbs or far side — occludes.

use rand::Rng;
use rand_distr::{Distribution, Normal};

use super::math::{norm, normalize, sub, V3};
use super::world::{PlacedPerson, World};
use posefuse_core::frame::Box2d;
use posefuse_core::geometry::box2d_from_points;
use posefuse_core::keypoints::K;

/// 2D annotation noise: σ = this fraction of the 2D box height...
pub const LABEL_NOISE_FRACTION: f64 = 0.015;
/// ...capped at this many image pixels.
pub const LABEL_NOISE_CAP_PX: f64 = 4.0;
/// `label-noise` effect: σ of the 3D keypoint labels' error per axis, as a fraction of the person's
/// height (the 2D labels' fraction: the same labeller's hand in both).
pub const LABEL_NOISE_3D_FRACTION: f64 = 0.015;
/// A keypoint counts as seen by the LiDAR (for 3D visibility) with a person return this close.
pub const LIDAR_SUPPORT_M: f64 = 0.25;

/// Labels of one person.
#[derive(Debug, Clone)]
pub struct PersonLabels {
    /// Exact projections (image pixels); NaN behind the camera.
    pub uv_true: [[f64; 2]; K],
    /// Annotator-like noisy labels (image pixels).
    pub uv_label: [[f64; 2]; K],
    pub visible_2d: [bool; K],
    /// Projects into the image but is not seen (labelled, occluded).
    pub occluded_2d: [bool; K],
    pub visible_3d: [bool; K],
    /// Neither seen by the camera nor supported by a LiDAR return (labelled, occluded).
    pub occluded_3d: [bool; K],
    pub box2d: Box2d,
    /// The 3D keypoint labels (vehicle frame): the joints themselves unless labelled with noise.
    pub xyz_3d: [V3; K],
}

impl PersonLabels {
    /// Adds a labeller's 3D error (`label-noise`): isotropic, σ = [`LABEL_NOISE_3D_FRACTION`] of
    /// the person's height per axis.
    pub fn with_3d_noise<R: Rng>(mut self, height: f64, rng: &mut R) -> PersonLabels {
        if let Ok(n) = Normal::new(0.0, LABEL_NOISE_3D_FRACTION * height) {
            for k in self.xyz_3d.iter_mut() {
                *k = [k[0] + n.sample(rng), k[1] + n.sample(rng), k[2] + n.sample(rng)];
            }
        }
        self
    }
}

/// Whether keypoint `k` of `p` is seen by the camera (the rule in the module docs).
pub fn keypoint_visible(world: &World, p: &PlacedPerson, k: usize) -> bool {
    let cam = &world.camera;
    let kp = p.keypoints[k];
    if !cam.project(kp).in_image {
        return false;
    }
    let o = cam.position();
    let v = sub(kp, o);
    let dist = norm(v);
    let d = normalize(v);
    let Some(hit) = world.scene.cast_all(o, d, dist + p.tolerance[k]) else {
        return false;
    };
    let Some(pi) = hit.prim else {
        return false;
    };
    let prim = &world.scene.prims[pi as usize];
    let at = super::math::madd(o, d, hit.t);
    prim.object == p.object
        && super::body::keypoint_parts(k).contains(&prim.part)
        && norm(sub(at, kp)) <= p.tolerance[k]
}

/// The tight box around the projected body surface (amodal: occluders ignored), clipped to the
/// image. `None` when nothing of the body lands in the image.
pub fn box_2d(world: &World, p: &PlacedPerson) -> Option<Box2d> {
    let cam = &world.camera;
    let mut pts: Vec<V3> = Vec::with_capacity(2048);
    for &i in &p.body_prims {
        world.scene.prims[i as usize].shape.surface_samples(&mut pts);
    }
    let (w, h) = (cam.width as f64, cam.height as f64);
    let uv = pts.iter().filter_map(|q| {
        let pr = cam.project(*q);
        pr.valid.then(|| [pr.uv[0].clamp(0.0, w), pr.uv[1].clamp(0.0, h)])
    });
    box2d_from_points(uv).filter(|b| b.width >= 2.0 && b.height >= 2.0)
}

/// All labels of a person; `lidar_person_points` are the returns on this person.
pub fn label_person<R: Rng>(
    world: &World,
    p: &PlacedPerson,
    lidar_person_points: &[V3],
    rng: &mut R,
) -> Option<PersonLabels> {
    let box2d = box_2d(world, p)?;
    let sigma = (LABEL_NOISE_FRACTION * box2d.height).min(LABEL_NOISE_CAP_PX);
    let noise = Normal::new(0.0, sigma).ok();
    let mut uv_true = [[f64::NAN; 2]; K];
    let mut uv_label = [[f64::NAN; 2]; K];
    let mut visible_2d = [false; K];
    let mut visible_3d = [false; K];
    let mut in_image = [false; K];
    for k in 0..K {
        let pr = world.camera.project(p.keypoints[k]);
        if pr.valid {
            uv_true[k] = pr.uv;
        }
        in_image[k] = pr.in_image;
        let (nx, ny) = match noise {
            Some(n) => (n.sample(rng), n.sample(rng)),
            None => (0.0, 0.0),
        };
        uv_label[k] = [uv_true[k][0] + nx, uv_true[k][1] + ny];
        visible_2d[k] = keypoint_visible(world, p, k);
        let supported = lidar_person_points.iter().any(|q| norm(sub(*q, p.keypoints[k])) <= LIDAR_SUPPORT_M);
        visible_3d[k] = visible_2d[k] || supported;
    }
    let seen_2d = visible_2d.iter().any(|&v| v);
    let seen_3d = visible_3d.iter().any(|&v| v);
    let occluded_2d = std::array::from_fn(|k| seen_2d && in_image[k] && !visible_2d[k]);
    let occluded_3d = visible_3d.map(|v| seen_3d && !v);
    Some(PersonLabels {
        uv_true,
        uv_label,
        visible_2d,
        occluded_2d,
        visible_3d,
        occluded_3d,
        box2d,
        xyz_3d: p.keypoints,
    })
}
