//! Samples one frame's world: vehicle sensors, street layout, labelled pedestrians, occluders,
//! background clutter, lighting and the camera's look (exposure, noise, blur).

use std::f64::consts::PI;

use rand::Rng;
use rand_distr::{Distribution, LogNormal};

use super::body::{Anthro, Part, Skeleton};
use super::hands::slim_hands;
use super::math::{add, dot, norm, rot_z, sub, V3};
use super::poses::{sample_person, Activity, PersonModel, Slot};
use super::raycast::Shape;
use super::realism::{Effect, Realism};
use super::scene::{Ground, Material, ObjectKind, Pattern, Scene};
use super::street::dress;
use posefuse_core::error::Result;
use posefuse_core::frame::{Box3d, CameraCalibration};
use posefuse_core::geometry::Camera;
use posefuse_core::keypoints::K;

/// The top LiDAR's origin in the vehicle frame (Waymo-like: about 2.1 m above the ground).
pub const LIDAR_ORIGIN: V3 = posefuse_core::pipeline::NOMINAL_LIDAR_ORIGIN;
/// Metres added on each side of the body's extent for the 3D box.
pub const BOX3D_MARGIN: f64 = 0.05;

/// A labelled pedestrian placed in the world.
#[derive(Debug, Clone)]
pub struct PlacedPerson {
    pub object: u32,
    pub model: PersonModel,
    pub position: V3,
    pub heading: f64,
    /// Keypoints in the vehicle frame.
    pub keypoints: [V3; K],
    pub tolerance: [f64; K],
    /// Indices of this person's body primitives (accessories excluded).
    pub body_prims: Vec<u32>,
    pub box3d: Box3d,
}

/// Image formation parameters of a frame.
#[derive(Debug, Clone, Copy)]
pub struct Look {
    pub exposure: f32,
    /// Sensor noise standard deviation in 8-bit levels.
    pub noise: f32,
    /// Horizontal motion-blur length in image pixels (0 = none).
    pub blur: u32,
    pub seed: u64,
}

/// One simulated frame before sensing.
#[derive(Debug, Clone)]
pub struct World {
    pub scene: Scene,
    pub camera: Camera,
    pub persons: Vec<PlacedPerson>,
    pub look: Look,
    pub lidar_origin: V3,
}

fn srgb(r: u8, g: u8, b: u8) -> [f32; 3] {
    [r, g, b].map(|v| (v as f32 / 255.0).powf(2.2))
}

const SKIN: [[u8; 3]; 8] = [
    [255, 224, 196],
    [241, 194, 167],
    [224, 172, 138],
    [205, 150, 110],
    [180, 120, 85],
    [141, 90, 62],
    [110, 70, 48],
    [80, 52, 38],
];
const HAIR: [[u8; 3]; 6] = [[20, 16, 14], [55, 38, 26], [95, 66, 40], [190, 160, 110], [150, 150, 150], [130, 60, 30]];

fn cloth<R: Rng>(rng: &mut R) -> [f32; 3] {
    if rng.random_bool(0.45) {
        // neutral: black, grey, white, navy, beige
        let palette = [[25, 25, 28], [70, 70, 75], [140, 140, 140], [225, 225, 220], [30, 40, 75], [190, 170, 135]];
        let c = palette[rng.random_range(0..palette.len())];
        return srgb(c[0], c[1], c[2]);
    }
    let h = rng.random_range(0.0..6.0f32);
    let s = rng.random_range(0.35..0.9f32);
    let v = rng.random_range(0.3..0.95f32);
    let x = v * s * (1.0 - ((h % 2.0) - 1.0).abs());
    let (r, g, b) = match h as u32 {
        0 => (v * s, x, 0.0),
        1 => (x, v * s, 0.0),
        2 => (0.0, v * s, x),
        3 => (0.0, x, v * s),
        4 => (x, 0.0, v * s),
        _ => (v * s, 0.0, x),
    };
    let m = v - v * s;
    [r + m, g + m, b + m].map(|c| c.clamp(0.0, 1.0).powf(2.2))
}

fn plain(c: [f32; 3]) -> Material {
    Material { base: c, alt: c, pattern: Pattern::Plain }
}

fn sample_range<R: Rng>(rng: &mut R) -> f64 {
    // Like Waymo pedestrians with camera labels: most at 5–30 m, a tail to 60 m.
    let r = if rng.random_bool(0.85) {
        LogNormal::new(14f64.ln(), 0.55).map(|d| d.sample(rng)).unwrap_or(14.0)
    } else {
        rng.random_range(3.0..60.0)
    };
    r.clamp(3.0, 60.0)
}

fn sample_camera<R: Rng>(rng: &mut R) -> Result<Camera> {
    let (yaw, pitch, roll) = (
        rng.random_range(-3f64..3.0).to_radians(),
        rng.random_range(-0.5f64..2.0).to_radians(),
        rng.random_range(-0.7f64..0.7).to_radians(),
    );
    let (cy, sy, cp, sp, cr, sr) = (yaw.cos(), yaw.sin(), pitch.cos(), pitch.sin(), roll.cos(), roll.sin());
    // R = Rz(yaw)·Ry(pitch)·Rx(roll); positive pitch looks down.
    let r = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ];
    let t = [rng.random_range(1.5..1.65), rng.random_range(-0.12..0.05), rng.random_range(1.85..2.0)];
    let mut ext = Vec::with_capacity(16);
    for i in 0..3 {
        ext.extend_from_slice(&[r[i][0], r[i][1], r[i][2], t[i]]);
    }
    ext.extend_from_slice(&[0.0, 0.0, 0.0, 1.0]);
    let f = rng.random_range(1990.0..2090.0);
    Camera::from_calibration(&CameraCalibration {
        intrinsic: vec![
            f,
            f * rng.random_range(0.998..1.002),
            960.0 + rng.random_range(-12.0..12.0),
            640.0 + rng.random_range(-12.0..12.0),
            rng.random_range(0.02..0.07),
            rng.random_range(-0.02..0.01),
            rng.random_range(-5e-4..5e-4),
            rng.random_range(-5e-4..5e-4),
            rng.random_range(-2e-3..2e-3),
        ],
        extrinsic: ext,
        width: 1920,
        height: 1280,
    })
}

/// Footprints already taken on the ground (x, y, radius), and how far from the road centre
/// people may stand.
struct Footprints {
    taken: Vec<[f64; 3]>,
    limit_y: f64,
}

impl Footprints {
    fn free(&self, x: f64, y: f64, r: f64) -> bool {
        let near_vehicle = x < 4.5 && y.abs() < 2.0 + r;
        !near_vehicle && self.taken.iter().all(|f| (f[0] - x).hypot(f[1] - y) >= f[2] + r)
    }
    fn take(&mut self, x: f64, y: f64, r: f64) {
        self.taken.push([x, y, r]);
    }
}

fn footprint_radius(a: Activity) -> f64 {
    match a {
        Activity::Cycling | Activity::Stroller => 0.95,
        Activity::Scooter => 0.6,
        _ => 0.45,
    }
}

/// Adds a person's primitives with a fresh outfit; returns the body primitive indices.
fn add_person<R: Rng>(rng: &mut R, scene: &mut Scene, object: u32, m: &PersonModel, pos: V3, heading: f64) -> Vec<u32> {
    let s = SKIN[rng.random_range(0..SKIN.len())];
    let skin = srgb(s[0], s[1], s[2]);
    let hc = HAIR[rng.random_range(0..HAIR.len())];
    let hair = if rng.random_bool(0.12) { cloth(rng) } else { srgb(hc[0], hc[1], hc[2]) };
    let shirt_c = cloth(rng);
    let shirt = match rng.random_range(0..10) {
        0..=5 => plain(shirt_c),
        6..=8 => Material { base: shirt_c, alt: cloth(rng), pattern: Pattern::Stripes(rng.random_range(0.03..0.12)) },
        _ => Material { base: shirt_c, alt: cloth(rng), pattern: Pattern::Checks(rng.random_range(0.04..0.1)) },
    };
    let pants_c = cloth(rng);
    let shoes = cloth(rng).map(|v| v * 0.7);
    let sk = &m.skeleton;
    let head = Material {
        base: skin,
        alt: hair,
        pattern: Pattern::Head { facing: rot_z(sk.facing, heading), up: rot_z(sk.head_up, heading) },
    };
    let long_sleeves = rng.random_bool(0.65);
    let shorts = rng.random_bool(0.2);
    let ids = [
        scene.add_material(plain(skin)),
        scene.add_material(head),
        scene.add_material(shirt),
        scene.add_material(if long_sleeves { shirt } else { plain(skin) }),
        scene.add_material(plain(pants_c)),
        scene.add_material(if shorts { plain(skin) } else { plain(pants_c) }),
        scene.add_material(plain(shoes)),
        scene.add_material(plain(cloth(rng))),
        scene.add_material(plain(cloth(rng).map(|v| v * 0.8))),
        scene.add_material(plain(srgb(25, 25, 25))),
    ];
    let slot_id = |s: Slot| match s {
        Slot::Skin => ids[0],
        Slot::Head => ids[1],
        Slot::Shirt => ids[2],
        Slot::Sleeve => ids[3],
        Slot::Pants => ids[4],
        Slot::Shin => ids[5],
        Slot::Shoes => ids[6],
        Slot::Gear => ids[7],
        Slot::Frame => ids[8],
        Slot::Tyre => ids[9],
    };
    let mut body = Vec::new();
    for (shape, part, slot) in &m.parts {
        if *part != Part::Accessory {
            body.push(scene.prims.len() as u32);
        }
        scene.add_prim(shape.placed(heading, pos), object, *part, slot_id(*slot));
    }
    let h = m.anthro.height;
    scene.shadows.push([
        pos[0] - scene.sun[0] / scene.sun[2] * 0.3 * h,
        pos[1] - scene.sun[1] / scene.sun[2] * 0.3 * h,
        0.4,
    ]);
    body
}

/// The tight heading-aligned box around some primitives plus `margin` on every side.
pub fn box_around(scene: &Scene, prims: &[u32], heading: f64, margin: f64) -> Box3d {
    let ux = [heading.cos(), heading.sin(), 0.0];
    let uy = [-heading.sin(), heading.cos(), 0.0];
    let uz = [0.0, 0.0, 1.0];
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for &i in prims {
        for (a, u) in [ux, uy, uz].into_iter().enumerate() {
            let (l, h) = scene.prims[i as usize].shape.extent(u);
            lo[a] = lo[a].min(l);
            hi[a] = hi[a].max(h);
        }
    }
    let mid: Vec<f64> = (0..3).map(|a| 0.5 * (lo[a] + hi[a])).collect();
    let c = add(add([ux[0] * mid[0], ux[1] * mid[0], 0.0], [uy[0] * mid[1], uy[1] * mid[1], 0.0]), [0.0, 0.0, mid[2]]);
    Box3d {
        center_x: c[0],
        center_y: c[1],
        center_z: c[2],
        length: hi[0] - lo[0] + 2.0 * margin,
        width: hi[1] - lo[1] + 2.0 * margin,
        height: hi[2] - lo[2] + 2.0 * margin,
        heading,
    }
}

/// Adds a parked car (body, cabin, wheels) centred at (x, y).
pub fn add_car<R: Rng>(rng: &mut R, scene: &mut Scene, x: f64, y: f64, yaw: f64) {
    let obj = scene.add_object(ObjectKind::Car);
    let body = scene.add_material(plain(cloth(rng)));
    let glass = scene.add_material(plain(srgb(30, 38, 48)));
    let tyre = scene.add_material(plain(srgb(22, 22, 22)));
    let (l, w) = (rng.random_range(4.0..5.0), rng.random_range(1.7..1.95));
    let hb = rng.random_range(0.75..1.0);
    let p = |q: V3| add(rot_z(q, yaw), [x, y, 0.0]);
    scene.add_prim(Shape::cuboid(p([0.0, 0.0, 0.3 + hb / 2.0]), [l, w, hb], yaw), obj, Part::Thing, body);
    let ch = rng.random_range(0.45..0.65);
    scene.add_prim(
        Shape::cuboid(p([-0.15 * l, 0.0, 0.3 + hb + ch / 2.0]), [0.55 * l, w * 0.9, ch], yaw),
        obj,
        Part::Thing,
        glass,
    );
    for (fx, fy) in [(0.33, 0.5), (0.33, -0.5), (-0.33, 0.5), (-0.33, -0.5)] {
        let axes = [rot_z([1.0, 0.0, 0.0], yaw), rot_z([0.0, 1.0, 0.0], yaw), [0.0, 0.0, 1.0]];
        scene.add_prim(
            Shape::ellipsoid(p([fx * l, fy * w * 0.95, 0.33]), axes, [0.33, 0.1, 0.33]),
            obj,
            Part::Thing,
            tyre,
        );
    }
    scene.shadows.push([x, y, 0.55 * l]);
}

fn add_pole<R: Rng>(rng: &mut R, scene: &mut Scene, x: f64, y: f64) {
    let obj = scene.add_object(ObjectKind::Pole);
    let m = scene.add_material(plain(srgb(
        rng.random_range(60..160),
        rng.random_range(60..160),
        rng.random_range(60..160),
    )));
    let (r, h) = (rng.random_range(0.05..0.16), rng.random_range(2.5..6.0));
    scene.add_prim(Shape::capsule([x, y, 0.0], [x, y, h], r), obj, Part::Thing, m);
    if rng.random_bool(0.3) {
        let sign = scene.add_material(plain(cloth(rng)));
        scene.add_prim(
            Shape::cuboid([x, y, h * 0.75], [0.05, 0.6, 0.6], rng.random_range(0.0..PI)),
            obj,
            Part::Thing,
            sign,
        );
    }
}

fn add_tree<R: Rng>(rng: &mut R, scene: &mut Scene, x: f64, y: f64) {
    let obj = scene.add_object(ObjectKind::Tree);
    let bark =
        scene.add_material(Material { base: srgb(70, 50, 35), alt: srgb(100, 75, 50), pattern: Pattern::Mottled(8.0) });
    let leaves =
        scene.add_material(Material { base: srgb(40, 80, 30), alt: srgb(90, 130, 50), pattern: Pattern::Mottled(5.0) });
    let h = rng.random_range(2.0..3.5);
    scene.add_prim(Shape::capsule([x, y, 0.0], [x, y, h], rng.random_range(0.1..0.2)), obj, Part::Thing, bark);
    let r = rng.random_range(1.2..2.5);
    let axes = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    scene.add_prim(Shape::ellipsoid([x, y, h + r * 0.8], axes, [r, r, r * 1.1]), obj, Part::Thing, leaves);
}

fn add_clutter<R: Rng>(rng: &mut R, scene: &mut Scene, x: f64, y: f64) {
    let obj = scene.add_object(ObjectKind::Clutter);
    let m = scene.add_material(plain(cloth(rng)));
    let axes = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    match rng.random_range(0..4) {
        0 => scene.add_prim(
            Shape::cuboid([x, y, 0.45], [0.55, 0.55, 0.9], rng.random_range(0.0..PI)),
            obj,
            Part::Thing,
            m,
        ),
        1 => scene.add_prim(Shape::capsule([x, y, 0.0], [x, y, 0.6], 0.13), obj, Part::Thing, m),
        2 => {
            let leaves = scene.add_material(Material {
                base: srgb(35, 70, 30),
                alt: srgb(80, 120, 45),
                pattern: Pattern::Mottled(6.0),
            });
            let r = rng.random_range(0.4..0.9);
            scene.add_prim(Shape::ellipsoid([x, y, r * 0.6], axes, [r, r, r * 0.8]), obj, Part::Thing, leaves)
        }
        _ => scene.add_prim(
            Shape::cuboid([x, y, 0.45], [1.6, 0.5, 0.45], rng.random_range(0.0..PI)),
            obj,
            Part::Thing,
            m,
        ),
    }
}

fn add_buildings<R: Rng>(rng: &mut R, scene: &mut Scene, road_half: f64) {
    for side in [1.0, -1.0] {
        let mut x = rng.random_range(-20.0..0.0);
        while x < 140.0 {
            let len = rng.random_range(8.0..30.0);
            let set = road_half + rng.random_range(5.0..12.0);
            let depth = 10.0;
            let h = rng.random_range(5.0..28.0);
            let obj = scene.add_object(ObjectKind::Building);
            let wall = cloth(rng).map(|v| 0.3 + 0.5 * v);
            let win = srgb(rng.random_range(20..90), rng.random_range(30..100), rng.random_range(40..120));
            let m = scene.add_material(Material {
                base: wall,
                alt: win,
                pattern: Pattern::Facade(rng.random_range(2.5..4.0)),
            });
            scene.add_prim(
                Shape::cuboid([x + len / 2.0, side * (set + depth / 2.0), h / 2.0], [len, depth, h], 0.0),
                obj,
                Part::Thing,
                m,
            );
            x += len + rng.random_range(0.0..8.0);
        }
    }
    let obj = scene.add_object(ObjectKind::Building);
    let m = scene.add_material(Material {
        base: srgb(150, 140, 130),
        alt: srgb(40, 50, 70),
        pattern: Pattern::Facade(3.0),
    });
    scene.add_prim(Shape::cuboid([150.0, 0.0, 15.0], [10.0, 120.0, 30.0], 0.0), obj, Part::Thing, m);
}

fn place_person<R: Rng>(
    rng: &mut R,
    scene: &mut Scene,
    feet: &mut Footprints,
    camera: &Camera,
    kind: ObjectKind,
    at: Option<(f64, f64)>,
    realism: Realism,
) -> Option<PlacedPerson> {
    let anthro = Anthro::sample(rng);
    let mut model = sample_person(rng, anthro, realism.has(Effect::ArmsIn));
    if realism.has(Effect::Dress) {
        dress(rng, &mut model);
    }
    if realism.has(Effect::SlimHands) {
        slim_hands(&mut model);
    }
    let fr = footprint_radius(model.activity);
    let cam = camera.position();
    let cam_yaw = {
        let f = sub(camera.to_vehicle([1.0, 0.0, 0.0]), cam);
        f[1].atan2(f[0])
    };
    for _ in 0..60 {
        let (x, y) = match at {
            Some(p) => p,
            None => {
                let r = sample_range(rng);
                let az = cam_yaw + rng.random_range(-0.42..0.42);
                (cam[0] + r * az.cos(), cam[1] + r * az.sin())
            }
        };
        // Stay on the street and its sidewalks (buildings start further out).
        if y.abs() > feet.limit_y || !feet.free(x, y, fr) {
            if at.is_some() {
                return None;
            }
            continue;
        }
        let centre = [x, y, 0.5 * model.anthro.height];
        if matches!(kind, ObjectKind::Person { label: Some(_) }) && !camera.project(centre).in_image {
            continue;
        }
        feet.take(x, y, fr);
        let heading = rng.random_range(0.0..std::f64::consts::TAU);
        return Some(put_person(rng, scene, model, [x, y, 0.0], heading, kind));
    }
    None
}

/// Puts a posed person into the scene at `pos` (on the ground) facing `heading`.
pub fn put_person<R: Rng>(
    rng: &mut R,
    scene: &mut Scene,
    model: PersonModel,
    pos: V3,
    heading: f64,
    kind: ObjectKind,
) -> PlacedPerson {
    let object = scene.add_object(kind);
    let body_prims = add_person(rng, scene, object, &model, pos, heading);
    let keypoints = model.skeleton.keypoints.map(|k| add(rot_z(k, heading), pos));
    let box3d = box_around(scene, &body_prims, heading, BOX3D_MARGIN);
    PlacedPerson {
        object,
        tolerance: Skeleton::visibility_tolerance(&model.anthro),
        model,
        position: pos,
        heading,
        keypoints,
        body_prims,
        box3d,
    }
}

/// Samples a frame with `n_labelled` labelled pedestrians (fewer only if placement fails).
pub fn sample_world<R: Rng>(rng: &mut R, n_labelled: usize, realism: impl Into<Realism>) -> Result<World> {
    let realism = realism.into();
    let camera = sample_camera(rng)?;
    let road_half = rng.random_range(4.5..9.0);
    let ground = Ground {
        road_half,
        asphalt: srgb(rng.random_range(45..85), rng.random_range(45..85), rng.random_range(45..88)),
        sidewalk: srgb(rng.random_range(120..175), rng.random_range(115..170), rng.random_range(105..165)),
        crosswalk: rng.random_bool(0.3).then(|| rng.random_range(6.0..30.0)),
        seed: rng.random(),
    };
    let mut scene = Scene::new(ground);
    let elev = rng.random_range(0.3f64..1.25);
    let az = rng.random_range(0.0..std::f64::consts::TAU);
    scene.sun = [elev.cos() * az.cos(), elev.cos() * az.sin(), elev.sin()];
    scene.ambient = rng.random_range(0.3..0.65);
    let overcast = scene.ambient > 0.55;
    scene.sky = if overcast { [[0.6, 0.62, 0.65], [0.8, 0.8, 0.82]] } else { [[0.2, 0.35, 0.75], [0.7, 0.78, 0.88]] };
    let mut feet = Footprints { taken: Vec::new(), limit_y: road_half + 4.5 };
    let mut persons = Vec::new();
    for i in 0..n_labelled {
        if let Some(p) =
            place_person(rng, &mut scene, &mut feet, &camera, ObjectKind::Person { label: Some(i) }, None, realism)
        {
            persons.push(p);
        }
    }
    let cam = camera.position();
    // Partial occluders on the line of sight to some labelled persons.
    let positions: Vec<V3> = persons.iter().map(|p| p.position).collect();
    for p in positions {
        if !rng.random_bool(0.3) {
            continue;
        }
        let v = sub(p, cam);
        let dist = norm([v[0], v[1], 0.0]);
        let dir = [v[0] / dist, v[1] / dist, 0.0];
        let perp = [-dir[1], dir[0], 0.0];
        for _ in 0..10 {
            let f = rng.random_range(0.35..0.85);
            let kind = rng.random_range(0..10);
            let lat = match kind {
                0..=2 => rng.random_range(-1.6..1.6),
                3..=5 => rng.random_range(-0.35..0.35),
                _ => rng.random_range(-0.8..0.8),
            };
            let q = add(add(cam, [dir[0] * dist * f, dir[1] * dist * f, 0.0]), [perp[0] * lat, perp[1] * lat, 0.0]);
            let (x, y) = (q[0], q[1]);
            let placed = match kind {
                0..=2 => {
                    if feet.free(x, y, 2.4) {
                        feet.take(x, y, 2.4);
                        let yaw = rng.random_range(-0.15..0.15) + if rng.random_bool(0.5) { 0.0 } else { PI };
                        add_car(rng, &mut scene, x, y, yaw);
                        true
                    } else {
                        false
                    }
                }
                3..=5 => {
                    if feet.free(x, y, 0.3) {
                        feet.take(x, y, 0.3);
                        add_pole(rng, &mut scene, x, y);
                        true
                    } else {
                        false
                    }
                }
                6..=8 => place_person(
                    rng,
                    &mut scene,
                    &mut feet,
                    &camera,
                    ObjectKind::Person { label: None },
                    Some((x, y)),
                    realism,
                )
                .is_some(),
                _ => {
                    if feet.free(x, y, 0.9) {
                        feet.take(x, y, 0.9);
                        add_clutter(rng, &mut scene, x, y);
                        true
                    } else {
                        false
                    }
                }
            };
            if placed {
                break;
            }
        }
    }
    // Street furniture and background.
    let side = |rng: &mut R| if rng.random_bool(0.5) { 1.0 } else { -1.0 };
    for _ in 0..rng.random_range(2..7) {
        let (x, y) = (rng.random_range(4.0..70.0), side(rng) * (road_half - rng.random_range(1.0..1.4)));
        if feet.free(x, y, 2.4) {
            feet.take(x, y, 2.4);
            let yaw = if rng.random_bool(0.5) { 0.0 } else { PI } + rng.random_range(-0.05..0.05);
            add_car(rng, &mut scene, x, y, yaw);
        }
    }
    for _ in 0..rng.random_range(2..7) {
        let (x, y) = (rng.random_range(3.0..70.0), side(rng) * (road_half + rng.random_range(0.4..1.2)));
        if feet.free(x, y, 0.3) {
            feet.take(x, y, 0.3);
            add_pole(rng, &mut scene, x, y);
        }
    }
    for _ in 0..rng.random_range(0..5) {
        let (x, y) = (rng.random_range(5.0..80.0), side(rng) * (road_half + rng.random_range(1.5..4.0)));
        if feet.free(x, y, 1.5) {
            feet.take(x, y, 1.5);
            add_tree(rng, &mut scene, x, y);
        }
    }
    for _ in 0..rng.random_range(1..6) {
        let (x, y) = (rng.random_range(4.0..60.0), side(rng) * (road_half + rng.random_range(0.5..4.0)));
        if feet.free(x, y, 0.9) {
            feet.take(x, y, 0.9);
            add_clutter(rng, &mut scene, x, y);
        }
    }
    for _ in 0..rng.random_range(0..4) {
        let (x, y) = (rng.random_range(4.0..60.0), rng.random_range(-14.0..14.0));
        place_person(rng, &mut scene, &mut feet, &camera, ObjectKind::Person { label: None }, Some((x, y)), realism);
    }
    add_buildings(rng, &mut scene, road_half);
    let look = Look {
        exposure: rng.random_range(0.75..1.35),
        noise: rng.random_range(1.0..4.0),
        blur: if rng.random_bool(0.12) { rng.random_range(2..9) } else { 0 },
        seed: rng.random(),
    };
    Ok(World { scene, camera, persons, look, lidar_origin: LIDAR_ORIGIN })
}

/// Horizontal distance from the LiDAR to a point.
pub fn lidar_range(p: V3) -> f64 {
    let v = sub(p, LIDAR_ORIGIN);
    dot([v[0], v[1], 0.0], [v[0], v[1], 0.0]).sqrt()
}
