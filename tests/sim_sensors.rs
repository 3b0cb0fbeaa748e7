//! The simulator's sensors agree with each other: LiDAR returns land on the pixels of the surface
//! they hit, occlusion labels agree with what the renderer shows, and camera rays match the
//! calibration.

use posefuse::geometry::nominal_camera;
use posefuse::geometry::Camera;
use posefuse::pipeline::NOMINAL_LIDAR_ORIGIN as LIDAR_ORIGIN;
use posefuse::sim::body::Anthro;
use posefuse::sim::body::Part;
use posefuse::sim::dataset::frame_rng;
use posefuse::sim::labels::{box_2d, keypoint_visible};
use posefuse::sim::lidar::{footprint_return, inclinations, nir_reflectivity, scan};
use posefuse::sim::math::{norm, normalize, sub};
use posefuse::sim::poses::{pose_person, sample_person, Activity};
use posefuse::sim::raycast::Shape;
use posefuse::sim::realism::{Effect, Realism};
use posefuse::sim::render::{render, RayGrid, Region, Rendered};
use posefuse::sim::scene::{Ground, ObjectKind, Scene, GROUND};
use posefuse::sim::scene::{Material, Pattern};
use posefuse::sim::street::{dress, Profile};
use posefuse::sim::world::{put_person, sample_world, Look, World};

/// The region of the image around a person's 2D box (clipped), coarse enough to stay small.
fn region_around(world: &World, b: &posefuse::frame::Box2d) -> Region {
    let cam = &world.camera;
    let m = 10.0;
    let x0 = (b.center_x - b.width / 2.0 - m).max(0.0).floor() as i64;
    let y0 = (b.center_y - b.height / 2.0 - m).max(0.0).floor() as i64;
    let x1 = ((b.center_x + b.width / 2.0 + m).ceil() as i64).min(cam.width as i64);
    let y1 = ((b.center_y + b.height / 2.0 + m).ceil() as i64).min(cam.height as i64);
    let step = ((x1 - x0).max(y1 - y0) / 300 + 1) as u32;
    Region { x0, y0, w: ((x1 - x0) as u32).div_ceil(step), h: ((y1 - y0) as u32).div_ceil(step), step }
}

/// The id at an image pixel and whether its 3×3 output neighbourhood shows one object only.
fn id_at(r: &Rendered, uv: [f64; 2]) -> Option<(u32, bool)> {
    let g = &r.region;
    let j = ((uv[0] - g.x0 as f64) / g.step as f64).floor() as i64;
    let i = ((uv[1] - g.y0 as f64) / g.step as f64).floor() as i64;
    if j < 1 || i < 1 || j + 1 >= g.w as i64 || i + 1 >= g.h as i64 {
        return None;
    }
    let id = r.ids[(i * g.w as i64 + j) as usize];
    let same = (-1..=1).all(|di| (-1..=1).all(|dj| r.ids[((i + di) * g.w as i64 + j + dj) as usize] == id));
    Some((id, same))
}

#[test]
fn lidar_returns_land_on_the_rendered_surface_they_hit() {
    let (mut eligible, mut agree, mut person_hits) = (0usize, 0usize, 0usize);
    for seed in 0..3u64 {
        let mut rng = frame_rng(1000 + seed, 0);
        let world = sample_world(&mut rng, 2, Profile::Clean).unwrap();
        let returns = scan(&world, Profile::Clean, &mut rng);
        let cam = &world.camera;
        for p in &world.persons {
            let Some(b) = box_2d(&world, p) else { continue };
            let rendered = render(&world, region_around(&world, &b));
            for r in &returns {
                let x = [r.xyz[0] as f64, r.xyz[1] as f64, r.xyz[2] as f64];
                let pr = cam.project(x);
                if !pr.in_front {
                    continue;
                }
                // Seen from the camera? (The LiDAR sits elsewhere, so some returns are hidden.)
                let o = cam.position();
                let dist = norm(sub(x, o));
                let hit = world.scene.cast_all(o, normalize(sub(x, o)), dist + 1.0);
                if hit.is_none_or(|h| h.t < dist - 0.08) {
                    continue;
                }
                let Some((id, homogeneous)) = id_at(&rendered, pr.uv) else { continue };
                if !homogeneous {
                    continue;
                }
                eligible += 1;
                if id == r.object {
                    agree += 1;
                    if r.object == p.object {
                        person_hits += 1;
                    }
                }
            }
        }
    }
    assert!(eligible > 300 && person_hits > 50, "too few checkable returns: {eligible} ({person_hits} on persons)");
    let frac = agree as f64 / eligible as f64;
    assert!(frac > 0.98, "only {agree}/{eligible} returns project onto the object they hit");
}

#[test]
fn visibility_flags_agree_with_the_rendered_image() {
    let (mut checked_visible, mut visible_ok, mut hidden_by_other) = (0usize, 0usize, 0usize);
    for seed in 0..4u64 {
        let mut rng = frame_rng(2000 + seed, 0);
        let world = sample_world(&mut rng, 3, Profile::Clean).unwrap();
        for p in &world.persons {
            let Some(b) = box_2d(&world, p) else { continue };
            let rendered = render(&world, region_around(&world, &b));
            for k in 0..13 {
                let pr = world.camera.project(p.keypoints[k]);
                let Some((id, homogeneous)) = id_at(&rendered, pr.uv) else { continue };
                let vis = keypoint_visible(&world, p, k);
                if vis {
                    checked_visible += 1;
                    visible_ok += usize::from(id == p.object);
                } else if homogeneous && id != p.object && id != GROUND {
                    hidden_by_other += 1;
                }
                if homogeneous && id != p.object && id != GROUND {
                    assert!(!vis, "keypoint {k} is labelled visible but object {id} covers its pixel");
                }
            }
        }
    }
    assert!(checked_visible > 40, "{checked_visible}");
    assert!(visible_ok as f64 >= 0.97 * checked_visible as f64, "{visible_ok}/{checked_visible}");
    let _ = hidden_by_other;
}

fn empty_world() -> World {
    let scene = Scene::new(Ground { road_half: 6.0, asphalt: [0.1; 3], sidewalk: [0.3; 3], crosswalk: None, seed: 1 });
    World {
        scene,
        camera: nominal_camera().unwrap(),
        persons: Vec::new(),
        look: Look { exposure: 1.0, noise: 0.0, blur: 0, seed: 0 },
        lidar_origin: LIDAR_ORIGIN,
    }
}

fn standing(seed: u64) -> posefuse::sim::poses::PersonModel {
    let mut rng = frame_rng(seed, 7);
    pose_person(&mut rng, Anthro::new(1.75, 1.0, |_| 1.0), Activity::Standing)
}

#[test]
fn self_occlusion_follows_the_viewpoint() {
    let mut rng = frame_rng(3, 3);
    // Facing the camera (heading π: the person looks back along −x toward the vehicle).
    let mut w = empty_world();
    let p = put_person(
        &mut rng,
        &mut w.scene,
        standing(1),
        [12.0, 0.0, 0.0],
        std::f64::consts::PI,
        ObjectKind::Person { label: Some(0) },
    );
    let front: Vec<bool> = (0..13).map(|k| keypoint_visible(&w, &p, k)).collect();
    assert!(front[0] && front[1] && front[2] && front[7] && front[8], "front view: {front:?}");
    // Facing away: the nose is behind the head.
    let mut w = empty_world();
    let p =
        put_person(&mut rng, &mut w.scene, standing(1), [12.0, 0.0, 0.0], 0.0, ObjectKind::Person { label: Some(0) });
    let back: Vec<bool> = (0..13).map(|k| keypoint_visible(&w, &p, k)).collect();
    assert!(!back[0] && back[1] && back[2], "back view: {back:?}");
    // Left side toward the camera (heading +90°: facing +y, its left points to −x).
    let mut w = empty_world();
    let p = put_person(
        &mut rng,
        &mut w.scene,
        standing(1),
        [12.0, 0.0, 0.0],
        std::f64::consts::FRAC_PI_2,
        ObjectKind::Person { label: Some(0) },
    );
    let side: Vec<bool> = (0..13).map(|k| keypoint_visible(&w, &p, k)).collect();
    assert!(side[1] && !side[2] && side[7] && !side[8], "side view: {side:?}");
}

#[test]
fn a_wall_in_front_hides_the_legs_only() {
    let mut rng = frame_rng(4, 4);
    let mut w = empty_world();
    let p = put_person(
        &mut rng,
        &mut w.scene,
        standing(2),
        [14.0, 0.0, 0.0],
        std::f64::consts::PI,
        ObjectKind::Person { label: Some(0) },
    );
    // A 1 m high wall 3 m in front of the person.
    let wall = w.scene.add_object(ObjectKind::Clutter);
    let m = w.scene.add_material(Material { base: [0.5; 3], alt: [0.5; 3], pattern: Pattern::Plain });
    w.scene.add_prim(Shape::cuboid([11.0, 0.0, 0.5], [0.4, 3.0, 1.0], 0.0), wall, Part::Thing, m);
    let v: Vec<bool> = (0..13).map(|k| keypoint_visible(&w, &p, k)).collect();
    assert!(v[0] && v[1] && v[2], "head and shoulders stay visible: {v:?}");
    assert!(!v[9] && !v[10] && !v[11] && !v[12], "knees and ankles are hidden: {v:?}");
    // The wall's returns are in front of the person's in the LiDAR too.
    w.persons.push(p);
    let pts = scan(&w, Profile::Clean, &mut rng);
    assert!(pts.iter().any(|r| r.object != GROUND && r.object != w.persons[0].object));
    assert!(pts.iter().any(|r| r.object == w.persons[0].object));
}

#[test]
fn interpolated_rays_match_the_camera_model() {
    let mut rng = frame_rng(5, 5);
    let world = sample_world(&mut rng, 1, Profile::Clean).unwrap();
    let cam: &Camera = &world.camera;
    let region = Region { x0: 37, y0: 11, w: 700, h: 500, step: 2 };
    let grid = RayGrid::new(cam, &region);
    for (j, i) in [(0.5, 0.5), (123.5, 77.5), (699.5, 499.5), (350.25, 260.75)] {
        let d = grid.dir(j, i);
        let want = cam.ray(region.center(j - 0.5, i - 0.5));
        let err = norm(sub(d, want));
        assert!(err < 2e-6, "pixel ({j}, {i}): {err}");
    }
}

#[test]
fn beams_span_the_waymo_field_of_view_densest_near_the_horizon() {
    let inc = inclinations().map(f64::to_degrees);
    assert!((inc[0] - 2.4).abs() < 1e-9 && (inc[63] + 17.6).abs() < 1e-9);
    let gaps: Vec<f64> = inc.windows(2).map(|w| w[0] - w[1]).collect();
    assert!(gaps.iter().all(|g| *g > 0.0));
    let near_horizon = gaps[15..22].iter().sum::<f64>() / 7.0;
    let bottom = gaps[56..].iter().sum::<f64>() / 7.0;
    assert!(bottom > 2.0 * near_horizon, "{near_horizon} vs {bottom}");
}

#[test]
fn street_clothes_and_items_never_move_a_keypoint() {
    let (mut holding, mut sleeved) = (0usize, 0usize);
    let n = 200;
    for seed in 0..n {
        let mut rng = frame_rng(seed, 1);
        let bare = pose_person(&mut rng, Anthro::new(1.7, 1.0, |_| 1.0), Activity::Walking);
        let mut dressed = bare.clone();
        dress(&mut rng, &mut dressed);
        assert_eq!(bare.skeleton.keypoints, dressed.skeleton.keypoints);
        let wrists = [5, 6].map(|k| bare.skeleton.keypoints[k]);
        let items: Vec<_> = dressed.parts[bare.parts.len()..].iter().filter(|p| p.1 == Part::Accessory).collect();
        // Something within reach of a wrist (a bag's strap ends at the shoulder, so the centre counts).
        if items.iter().any(|(s, _, _)| wrists.iter().any(|w| norm(sub(s.bounding_sphere().0, *w)) < 0.4)) {
            holding += 1;
        }
        let forearm_past_wrist = dressed.parts.iter().any(|(s, part, _)| match (s, part) {
            (Shape::Capsule { b, .. }, Part::Forearm(side)) => norm(sub(*b, wrists[*side])) > 0.01,
            _ => false,
        });
        sleeved += usize::from(forearm_past_wrist);
    }
    // Half of the walkers hold something and 55 % wear loose sleeves (binomial, n = 200).
    assert!((70..=130).contains(&holding), "{holding}/{n} hold something");
    assert!((85..=135).contains(&sleeved), "{sleeved}/{n} have sleeves over the wrist");
}

#[test]
fn street_lidar_mixes_ranges_at_silhouette_edges_only() {
    // A person 12 m ahead in front of a wall at 15 m: between the two there is nothing to hit.
    let gap_returns = |profile: Profile| {
        let mut rng = frame_rng(8, 8);
        let mut w = empty_world();
        let p = put_person(
            &mut rng,
            &mut w.scene,
            standing(3),
            [12.0, 0.0, 0.0],
            0.0,
            ObjectKind::Person { label: Some(0) },
        );
        let wall = w.scene.add_object(ObjectKind::Clutter);
        let m = w.scene.add_material(Material { base: [0.5; 3], alt: [0.5; 3], pattern: Pattern::Plain });
        w.scene.add_prim(Shape::cuboid([15.2, 0.0, 1.5], [0.4, 8.0, 3.0], 0.0), wall, Part::Thing, m);
        w.persons.push(p);
        let pts = scan(&w, profile, &mut rng);
        assert!(pts.len() > 200, "{}", pts.len());
        pts.iter().filter(|r| r.xyz[2] > 0.2 && r.xyz[0] > 12.7 && r.xyz[0] < 14.8).count()
    };
    assert_eq!(gap_returns(Profile::Clean), 0);
    let mixed = gap_returns(Profile::Street);
    assert!(mixed >= 5, "only {mixed} mixed returns between the person and the wall");
}

/// A person at `range` m straight ahead and a 1.5 cm thin pole beside them; returns of the scan.
fn person_and_pole(range: f64, realism: Realism) -> (World, Vec<posefuse::sim::lidar::Return>, u32) {
    let mut rng = frame_rng(9, 9);
    let mut w = empty_world();
    let p =
        put_person(&mut rng, &mut w.scene, standing(4), [range, 0.0, 0.0], 0.0, ObjectKind::Person { label: Some(0) });
    let pole = w.scene.add_object(ObjectKind::Pole);
    let m = w.scene.add_material(Material { base: [0.5; 3], alt: [0.5; 3], pattern: Pattern::Plain });
    w.scene.add_prim(Shape::capsule([range, 1.0, 0.0], [range, 1.0, 2.0], 0.015), pole, Part::Thing, m);
    w.persons.push(p);
    let pts = scan(&w, realism, &mut rng);
    (w, pts, pole)
}

#[test]
fn a_beam_footprint_makes_thin_things_look_thicker() {
    let pole_points = |realism: Realism| {
        let (_, pts, pole) = person_and_pole(20.0, realism);
        let on: Vec<f64> = pts.iter().filter(|r| r.object == pole).map(|r| (r.xyz[1] as f64 - 1.0).abs()).collect();
        (on.len(), on.iter().copied().fold(0.0, f64::max))
    };
    let (n_ray, wide_ray) = pole_points(Realism::from(Profile::Clean));
    let (n_cone, wide_cone) = pole_points(Realism::of(Profile::Clean, &[Effect::Footprint]));
    // At 20 m a column is 4.7 cm wide, the footprint 6 cm: the 3 cm pole is caught by more beams,
    // and its returns lie up to the footprint's radius (3 cm) beside it.
    assert!(n_cone as f64 > 1.5 * n_ray as f64, "{n_ray} returns from rays, {n_cone} from footprints");
    assert!(wide_ray < 0.02, "ray returns lie on the pole: {wide_ray}");
    assert!(wide_cone > 0.025 && wide_cone < 0.05, "footprint returns up to its radius aside: {wide_cone}");
}

#[test]
fn a_footprint_across_two_close_surfaces_returns_a_range_between_them() {
    // A 20 cm deep step seen edge-on at 15 m: footprints across it merge both ranges into one pulse.
    let mut scene =
        Scene::new(Ground { road_half: 6.0, asphalt: [0.1; 3], sidewalk: [0.3; 3], crosswalk: None, seed: 1 });
    let obj = scene.add_object(ObjectKind::Clutter);
    let m = scene.add_material(Material { base: [0.5; 3], alt: [0.5; 3], pattern: Pattern::Plain });
    scene.add_prim(Shape::cuboid([15.0, -1.0, 2.0], [0.2, 2.0, 4.0], 0.0), obj, Part::Thing, m);
    scene.add_prim(Shape::cuboid([15.2, 1.0, 2.0], [0.2, 2.0, 4.0], 0.0), obj, Part::Thing, m);
    let cands = [0u32, 1];
    let o = [0.0, 0.0, 2.0];
    let ranges: Vec<f64> =
        (-40..=40).filter_map(|i| footprint_return(&scene, o, 0.0, i as f64 * 2e-5, &cands).map(|h| h.t)).collect();
    assert_eq!(ranges.len(), 81);
    let between = ranges.iter().filter(|&&t| t > 14.92 && t < 15.08).count();
    assert!(between >= 5, "mixed ranges across the step: {ranges:?}");
    assert!(ranges.iter().all(|&t| t > 14.89 && t < 15.11), "{ranges:?}");
}

#[test]
fn dark_surfaces_drop_out_at_range_and_not_up_close() {
    let returns = |range: f64, effects: &[Effect], albedo: f32| {
        let mut rng = frame_rng(10, 10);
        let mut w = empty_world();
        let p = put_person(
            &mut rng,
            &mut w.scene,
            standing(4),
            [range, 0.0, 0.0],
            0.0,
            ObjectKind::Person { label: Some(0) },
        );
        for m in w.scene.materials.iter_mut() {
            m.base = [albedo; 3];
        }
        let object = p.object;
        w.persons.push(p);
        scan(&w, Realism::of(Profile::Clean, effects), &mut rng).iter().filter(|r| r.object == object).count() as f64
    };
    let kept = |range: f64, albedo: f32| returns(range, &[Effect::Reflectivity], albedo) / returns(range, &[], albedo);
    assert!(kept(8.0, 0.01) > 0.95, "near dark clothes stay: {}", kept(8.0, 0.01));
    assert!(kept(40.0, 0.01) < 0.75, "far dark clothes drop: {}", kept(40.0, 0.01));
    assert!(kept(40.0, 0.6) > kept(40.0, 0.01) + 0.15, "bright clothes return more at 40 m");
    assert!(nir_reflectivity([0.0; 3]) < nir_reflectivity([0.3; 3]));
}

#[test]
fn arms_in_puts_free_arms_against_the_torso_and_hides_pocketed_hands() {
    let (mut pocketed, mut close_wrists, mut close_without) = (0usize, 0usize, 0usize);
    let n = 400;
    for seed in 0..n {
        let a = Anthro::new(1.7, 1.0, |_| 1.0);
        let with = sample_person(&mut frame_rng(seed, 2), a.clone(), true);
        let without = sample_person(&mut frame_rng(seed, 2), a, false);
        let hands =
            |m: &posefuse::sim::poses::PersonModel| m.parts.iter().filter(|p| matches!(p.1, Part::Hand(_))).count();
        assert_eq!(hands(&without), 2);
        pocketed += usize::from(hands(&with) < 2);
        // A wrist less than 20 cm out from the body's midline is against the torso (hanging arms
        // are 20-30 cm out: half a shoulder width and a little abduction).
        let near_axis = |m: &posefuse::sim::poses::PersonModel| {
            [5, 6].iter().any(|&k| {
                let outward = if k == 5 { 1.0 } else { -1.0 };
                outward * (m.skeleton.keypoints[k][1] - m.skeleton.pelvis[1]) < 0.2
            })
        };
        close_wrists += usize::from(near_axis(&with));
        close_without += usize::from(near_axis(&without));
        let mut dressed = with.clone();
        dress(&mut frame_rng(seed, 3), &mut dressed);
        for s in 0..2 {
            if with.busy_hands[s] {
                let w = with.skeleton.keypoints[5 + s];
                let items = dressed.parts[with.parts.len()..].iter().filter(|p| p.1 == Part::Accessory);
                assert!(items.into_iter().all(|(sh, _, _)| norm(sub(sh.bounding_sphere().0, w)) > 0.12), "seed {seed}");
            }
        }
    }
    // 63 % of persons have free arms, 45 % of those hold them in; 60 % of styles are pockets.
    assert!((40..=100).contains(&pocketed), "{pocketed}/{n} with a hand in a pocket");
    assert!(close_wrists > close_without + 50, "{close_wrists} vs {close_without} wrists against the torso");
}
