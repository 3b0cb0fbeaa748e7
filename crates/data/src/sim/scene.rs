//! The scene: primitives with owners and materials, the ground, the light, and the first-hit query
//! shared by the LiDAR, the camera renderer and the occlusion labels.

use super::body::Part;
use super::math::{hash, madd, unit, value_noise, V3};
use super::raycast::{ground_hit, ray_may_hit_sphere, Shape};

/// Uncorrelated texture grain in [0, 1) on cells of 1/`freq` metres (cheaper than value noise).
#[inline]
fn grain(seed: u64, x: f64, y: f64, freq: f64) -> f32 {
    unit(hash(&[seed, (x * freq).floor() as i64 as u64, (y * freq).floor() as i64 as u64])) as f32
}

/// Object id of the ground and the sky in id buffers and LiDAR returns.
pub const GROUND: u32 = 0;

/// What an object is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ObjectKind {
    Ground,
    /// A pedestrian; `label` is its index among the frame's labelled persons.
    Person {
        label: Option<usize>,
    },
    Car,
    Pole,
    Tree,
    Building,
    Clutter,
}

/// Surface pattern on top of a material's base colour.
#[derive(Debug, Clone, Copy)]
pub enum Pattern {
    Plain,
    /// Horizontal stripes (period in metres).
    Stripes(f64),
    /// Checks of the given cell size (metres).
    Checks(f64),
    /// Skin face in front, hair on the back and top.
    Head {
        facing: V3,
        up: V3,
    },
    /// Windows on a façade (cell size in metres).
    Facade(f64),
    /// Mottled (foliage, bark): noise at the given frequency (1/m).
    Mottled(f64),
}

/// Linear-RGB albedo and pattern.
#[derive(Debug, Clone, Copy)]
pub struct Material {
    pub base: [f32; 3],
    pub alt: [f32; 3],
    pub pattern: Pattern,
}

/// One solid with its bounding sphere, owner and material.
#[derive(Debug, Clone, Copy)]
pub struct Prim {
    pub shape: Shape,
    pub center: V3,
    pub radius: f64,
    pub object: u32,
    pub part: Part,
    pub material: u32,
}

/// Ground appearance.
#[derive(Debug, Clone)]
pub struct Ground {
    pub road_half: f64,
    pub asphalt: [f32; 3],
    pub sidewalk: [f32; 3],
    pub crosswalk: Option<f64>,
    pub seed: u64,
}

/// A full scene.
#[derive(Debug, Clone)]
pub struct Scene {
    pub prims: Vec<Prim>,
    pub materials: Vec<Material>,
    pub objects: Vec<ObjectKind>,
    pub ground: Ground,
    /// Unit vector toward the sun.
    pub sun: V3,
    pub ambient: f32,
    pub sky: [[f32; 3]; 2],
    /// Soft ground shadows: (centre x, y, radius).
    pub shadows: Vec<[f64; 3]>,
}

/// First hit along a ray.
#[derive(Debug, Clone, Copy)]
pub struct Hit {
    pub t: f64,
    /// Primitive index; `None` for the ground.
    pub prim: Option<u32>,
    pub normal: V3,
}

impl Scene {
    pub fn new(ground: Ground) -> Scene {
        Scene {
            prims: Vec::new(),
            materials: Vec::new(),
            objects: vec![ObjectKind::Ground],
            ground,
            sun: [0.3, 0.4, 0.866],
            ambient: 0.45,
            sky: [[0.35, 0.5, 0.8], [0.75, 0.8, 0.85]],
            shadows: Vec::new(),
        }
    }

    pub fn add_object(&mut self, kind: ObjectKind) -> u32 {
        self.objects.push(kind);
        (self.objects.len() - 1) as u32
    }

    pub fn add_material(&mut self, m: Material) -> u32 {
        self.materials.push(m);
        (self.materials.len() - 1) as u32
    }

    pub fn add_prim(&mut self, shape: Shape, object: u32, part: Part, material: u32) {
        let (center, radius) = shape.bounding_sphere();
        self.prims.push(Prim { shape, center, radius, object, part, material });
    }

    /// Object id of a hit (`GROUND` for the ground).
    pub fn object_of(&self, h: &Hit) -> u32 {
        h.prim.map_or(GROUND, |p| self.prims[p as usize].object)
    }

    /// First hit among the candidate primitives and the ground, closer than `t_max`.
    pub fn cast(&self, o: V3, d: V3, candidates: &[u32], t_max: f64) -> Option<Hit> {
        self.cast_iter(o, d, candidates.iter().copied(), t_max)
    }

    fn cast_iter(&self, o: V3, d: V3, candidates: impl Iterator<Item = u32>, t_max: f64) -> Option<Hit> {
        let mut best = ground_hit(o, d).filter(|t| *t < t_max).map(|t| Hit { t, prim: None, normal: [0.0, 0.0, 1.0] });
        for i in candidates {
            let p = &self.prims[i as usize];
            let limit = best.map_or(t_max, |b| b.t);
            if !ray_may_hit_sphere(o, d, p.center, p.radius, limit) {
                continue;
            }
            if let Some((t, n)) = p.shape.intersect(o, d, 1e-6) {
                if t < limit {
                    best = Some(Hit { t, prim: Some(i), normal: n });
                }
            }
        }
        best
    }

    /// [`Scene::cast`] against every primitive.
    pub fn cast_all(&self, o: V3, d: V3, t_max: f64) -> Option<Hit> {
        self.cast_iter(o, d, 0..self.prims.len() as u32, t_max)
    }

    /// Linear-RGB albedo at a hit point.
    pub fn albedo(&self, h: &Hit, p: V3) -> [f32; 3] {
        let Some(pi) = h.prim else {
            return self.ground_albedo(p);
        };
        let prim = &self.prims[pi as usize];
        let m = &self.materials[prim.material as usize];
        let pick = |alt: bool| if alt { m.alt } else { m.base };
        let fine = 0.92 + 0.16 * grain(pi as u64, p[0] + p[1], p[2], 40.0);
        let c = match m.pattern {
            Pattern::Plain => m.base,
            Pattern::Stripes(period) => pick((p[2] / period).rem_euclid(1.0) < 0.5),
            Pattern::Checks(cell) => {
                let a = ((p[0] + p[1]) / cell).floor() as i64 + (p[2] / cell).floor() as i64;
                pick(a.rem_euclid(2) == 0)
            }
            Pattern::Head { facing, up } => {
                let n = h.normal;
                let f = n[0] * facing[0] + n[1] * facing[1] + n[2] * facing[2];
                let u = n[0] * up[0] + n[1] * up[1] + n[2] * up[2];
                pick(f < -0.15 || u > 0.55 - 0.3 * f.max(0.0))
            }
            Pattern::Facade(cell) => {
                let local = match prim.shape {
                    Shape::Box { c, cs: [co, s], .. } => {
                        let (dx, dy) = (p[0] - c[0], p[1] - c[1]);
                        (co * dx + s * dy) + (-s * dx + co * dy)
                    }
                    _ => p[0] + p[1],
                };
                let wu = (local / cell).rem_euclid(1.0);
                let wz = (p[2] / (cell * 1.1)).rem_euclid(1.0);
                pick(p[2] > 1.0 && (0.2..0.75).contains(&wu) && (0.3..0.8).contains(&wz))
            }
            Pattern::Mottled(f) => {
                let v = value_noise(pi as u64 ^ 0x55, (p[0] + p[1]) * f, p[2] * f) as f32;
                let mut out = [0.0; 3];
                for (i, o) in out.iter_mut().enumerate() {
                    *o = m.base[i] + (m.alt[i] - m.base[i]) * v;
                }
                out
            }
        };
        c.map(|v| v * fine)
    }

    fn ground_albedo(&self, p: V3) -> [f32; 3] {
        let g = &self.ground;
        let n1 = value_noise(g.seed, p[0] * 6.0, p[1] * 6.0) as f32;
        let n2 = grain(g.seed ^ 1, p[0], p[1], 40.0);
        let grain = 0.8 + 0.25 * n1 + 0.15 * n2;
        let y = p[1].abs();
        if y > g.road_half {
            let tile = (p[0] / 0.6).rem_euclid(1.0) < 0.04 || ((y - g.road_half) / 0.6).rem_euclid(1.0) < 0.04;
            let k = if tile { 0.7 } else { 1.0 } * grain;
            return g.sidewalk.map(|v| v * k);
        }
        let white = [0.75f32, 0.75, 0.72];
        if let Some(cx) = g.crosswalk {
            if (cx..cx + 3.5).contains(&p[0]) && (p[1] / 0.6).rem_euclid(1.0) < 0.5 {
                return white.map(|v| v * grain);
            }
        }
        let lane =
            ((y - 1.8).abs() < 0.07 && (p[0] / 9.0).rem_euclid(1.0) < 0.35) || (y - (g.road_half - 0.3)).abs() < 0.08;
        if lane {
            return white.map(|v| v * grain);
        }
        g.asphalt.map(|v| v * grain)
    }

    /// Fraction of direct sunlight reaching a ground point (soft blob shadows).
    pub fn ground_shadow(&self, p: V3) -> f32 {
        let mut light = 1.0f32;
        for s in &self.shadows {
            let (dx, dy) = (p[0] - s[0], p[1] - s[1]);
            let d2 = (dx * dx + dy * dy) / (s[2] * s[2]);
            if d2 < 1.0 {
                light = light.min(0.35 + 0.65 * d2 as f32);
            }
        }
        light
    }

    /// The point at distance `t` along a ray.
    pub fn point(o: V3, d: V3, t: f64) -> V3 {
        madd(o, d, t)
    }
}
