//! The camera: renders any pixel region of the 1920×1280 image by ray casting the scene through
//! the distorted lens (rays from `Camera`'s undistortion), with Lambert shading, textures, soft
//! ground shadows, exposure, optional horizontal motion blur and per-pixel sensor noise.
//!
//! A region can be rendered at a coarser `step` (one ray per step×step block of image pixels);
//! training-only crops use this to render the crop window at about twice the crop resolution.
//! Noise is a hash of the image pixel, so overlapping regions rendered separately agree.

use image::RgbImage;

use super::math::{dot, hash, normalize, sub, V3};
use super::scene::{Scene, GROUND};
use super::world::World;
use posefuse_core::geometry::Camera;

/// A rectangle of image pixels rendered at `step`: output pixel (j, i) covers image pixels
/// `[x0 + step·j, x0 + step·(j+1)) × [y0 + step·i, y0 + step·(i+1))`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Region {
    pub x0: i64,
    pub y0: i64,
    pub w: u32,
    pub h: u32,
    pub step: u32,
}

impl Region {
    /// The whole image at full resolution.
    pub fn full(cam: &Camera) -> Region {
        Region { x0: 0, y0: 0, w: cam.width, h: cam.height, step: 1 }
    }

    /// Image-pixel coordinates of the centre of output pixel (j, i).
    pub fn center(&self, j: f64, i: f64) -> [f64; 2] {
        self.point(j + 0.5, i + 0.5)
    }

    /// Image-pixel coordinates of the continuous output position (j, i).
    pub fn point(&self, j: f64, i: f64) -> [f64; 2] {
        let s = self.step as f64;
        [self.x0 as f64 + s * j, self.y0 as f64 + s * i]
    }
}

/// Rendered pixels and, per pixel, the object id of the first hit (`GROUND` for ground and sky).
pub struct Rendered {
    pub image: RgbImage,
    pub ids: Vec<u32>,
    pub region: Region,
}

const NODE: usize = 8;
const TILE: usize = 16;

/// Ray directions through output pixels: exact `Camera` undistortion on a coarse node grid,
/// bilinear in between (the lens model is smooth, the error is far below a pixel).
pub struct RayGrid {
    origin: V3,
    axes: [V3; 3],
    nw: usize,
    nodes: Vec<[f64; 2]>,
}

impl RayGrid {
    pub fn new(cam: &Camera, region: &Region) -> RayGrid {
        let origin = cam.position();
        let axes = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]].map(|e| sub(cam.to_vehicle(e), origin));
        let (w, h) = (region.w as usize, region.h as usize);
        let nw = w.div_ceil(NODE) + 1;
        let nh = h.div_ceil(NODE) + 1;
        let mut nodes = Vec::with_capacity(nw * nh);
        for ni in 0..nh {
            for nj in 0..nw {
                let [u, v] = region.point((nj * NODE) as f64, (ni * NODE) as f64);
                nodes.push(cam.undistort((u - cam.cu) / cam.fu, (v - cam.cv) / cam.fv).into());
            }
        }
        RayGrid { origin, axes, nw, nodes }
    }

    pub fn origin(&self) -> V3 {
        self.origin
    }

    /// The node values interpolated to row position `i` (one per node column).
    pub fn row(&self, i: f64, out: &mut [[f64; 2]]) {
        let gi = i / NODE as f64;
        let ni = (gi.floor() as usize).min(self.nodes.len() / self.nw - 2);
        let fi = gi - ni as f64;
        let (top, bot) =
            (&self.nodes[ni * self.nw..(ni + 1) * self.nw], &self.nodes[(ni + 1) * self.nw..(ni + 2) * self.nw]);
        for ((o, t), b) in out.iter_mut().zip(top).zip(bot) {
            *o = [t[0] + (b[0] - t[0]) * fi, t[1] + (b[1] - t[1]) * fi];
        }
    }

    /// [`RayGrid::dir`] from a row prepared by [`RayGrid::row`].
    #[inline]
    pub fn dir_in_row(&self, row: &[[f64; 2]], j: f64) -> V3 {
        let gj = j / NODE as f64;
        let nj = (gj.floor() as usize).min(self.nw - 2);
        let fj = gj - nj as f64;
        let (a, b) = (row[nj], row[nj + 1]);
        self.direction([a[0] + (b[0] - a[0]) * fj, a[1] + (b[1] - a[1]) * fj])
    }

    #[inline]
    fn direction(&self, uv: [f64; 2]) -> V3 {
        let [ax, ay, az] = self.axes;
        normalize([
            ax[0] - ay[0] * uv[0] - az[0] * uv[1],
            ax[1] - ay[1] * uv[0] - az[1] * uv[1],
            ax[2] - ay[2] * uv[0] - az[2] * uv[1],
        ])
    }

    /// Unit direction through the continuous output position (j, i); pixel (j, i)'s centre is
    /// at (j + 0.5, i + 0.5).
    pub fn dir(&self, j: f64, i: f64) -> V3 {
        let (gj, gi) = (j / NODE as f64, i / NODE as f64);
        let (nj, ni) =
            ((gj.floor() as usize).min(self.nw - 2), (gi.floor() as usize).min(self.nodes.len() / self.nw - 2));
        let (fj, fi) = (gj - nj as f64, gi - ni as f64);
        let n = |a: usize, b: usize| self.nodes[(ni + b) * self.nw + nj + a];
        let mut uv = [0.0; 2];
        for (k, item) in uv.iter_mut().enumerate() {
            let top = n(0, 0)[k] + (n(1, 0)[k] - n(0, 0)[k]) * fj;
            let bot = n(0, 1)[k] + (n(1, 1)[k] - n(0, 1)[k]) * fj;
            *item = top + (bot - top) * fi;
        }
        self.direction(uv)
    }
}

/// Primitives whose bounding sphere may be seen inside the cone through a pixel rectangle.
fn cone_candidates(
    scene: &Scene,
    rays: &RayGrid,
    j0: usize,
    i0: usize,
    j1: usize,
    i1: usize,
    from: &[u32],
) -> Vec<u32> {
    let corners = [
        rays.dir(j0 as f64, i0 as f64),
        rays.dir(j1 as f64, i0 as f64),
        rays.dir(j0 as f64, i1 as f64),
        rays.dir(j1 as f64, i1 as f64),
    ];
    let axis = normalize(corners.iter().fold([0.0; 3], |a, c| [a[0] + c[0], a[1] + c[1], a[2] + c[2]]));
    let cos_half = corners.iter().map(|c| dot(*c, axis)).fold(1.0, f64::min);
    let half = cos_half.clamp(-1.0, 1.0).acos() + 2e-3;
    let o = rays.origin();
    from.iter()
        .copied()
        .filter(|&p| {
            let prim = &scene.prims[p as usize];
            let v = sub(prim.center, o);
            let d = dot(v, v).sqrt();
            if d <= prim.radius {
                return true;
            }
            let ang = (dot(v, axis) / d).clamp(-1.0, 1.0).acos();
            ang <= half + (prim.radius / d).asin()
        })
        .collect()
}

/// Linear radiance of the first hit along a ray (sky when nothing is hit).
pub fn shade(scene: &Scene, o: V3, d: V3, cands: &[u32]) -> ([f32; 3], u32) {
    match scene.cast(o, d, cands, 400.0) {
        Some(hit) => {
            let p = Scene::point(o, d, hit.t);
            let a = scene.albedo(&hit, p);
            let sun = dot(hit.normal, scene.sun).max(0.0) as f32;
            let direct = if hit.prim.is_none() { sun * scene.ground_shadow(p) } else { sun };
            let sky = 0.15 * (0.5 + 0.5 * hit.normal[2] as f32);
            let light = scene.ambient + (1.0 - scene.ambient) * direct + sky;
            (a.map(|v| v * light), scene.object_of(&hit))
        }
        None => {
            let t = ((d[2] * 4.0).clamp(0.0, 1.0)) as f32;
            let [top, hor] = scene.sky;
            ([0, 1, 2].map(|c| hor[c] + (top[c] - hor[c]) * t), GROUND)
        }
    }
}

const GAMMA_STEPS: usize = 4096;

/// Linear [0, 1] → 8-bit level with gamma 2.2, tabulated over the square root of the linear
/// value so that dark tones keep their resolution.
fn gamma_table() -> &'static [f32; GAMMA_STEPS] {
    static TABLE: std::sync::OnceLock<[f32; GAMMA_STEPS]> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        std::array::from_fn(|i| {
            let r = i as f32 / (GAMMA_STEPS - 1) as f32;
            (r * r).powf(1.0 / 2.2) * 255.0
        })
    })
}

/// Renders a region of the world's camera image.
pub fn render(world: &World, region: Region) -> Rendered {
    let scene = &world.scene;
    let rays = RayGrid::new(&world.camera, &region);
    let (w, h) = (region.w as usize, region.h as usize);
    let mut lin = vec![[0.0f32; 3]; w * h];
    let mut ids = vec![GROUND; w * h];
    let all: Vec<u32> = (0..scene.prims.len() as u32).collect();
    let o = rays.origin();
    let row_len = rays.nw;
    let mut row_nodes = vec![[0.0f64; 2]; row_len];
    const SUPER: usize = 64;
    for si in (0..h).step_by(SUPER) {
        for sj in (0..w).step_by(SUPER) {
            let (sj1, si1) = ((sj + SUPER).min(w), (si + SUPER).min(h));
            let coarse = cone_candidates(scene, &rays, sj, si, sj1, si1, &all);
            for ti in (si..si1).step_by(TILE) {
                for tj in (sj..sj1).step_by(TILE) {
                    let (tj1, ti1) = ((tj + TILE).min(w), (ti + TILE).min(h));
                    let cands = cone_candidates(scene, &rays, tj, ti, tj1, ti1, &coarse);
                    for i in ti..ti1 {
                        rays.row(i as f64 + 0.5, &mut row_nodes);
                        for j in tj..tj1 {
                            let d = rays.dir_in_row(&row_nodes, j as f64 + 0.5);
                            let (c, id) = shade(scene, o, d, &cands);
                            lin[i * w + j] = c;
                            ids[i * w + j] = id;
                        }
                    }
                }
            }
        }
    }
    let look = &world.look;
    if look.blur > 0 {
        let len = (look.blur as usize).div_ceil(region.step as usize).max(1);
        if len > 1 {
            for row in lin.chunks_mut(w) {
                let src = row.to_vec();
                for (j, px) in row.iter_mut().enumerate() {
                    let (a, b) = (j.saturating_sub(len / 2), (j + len - len / 2).min(w));
                    let mut acc = [0.0f32; 3];
                    for s in &src[a..b] {
                        for c in 0..3 {
                            acc[c] += s[c];
                        }
                    }
                    *px = acc.map(|v| v / (b - a) as f32);
                }
            }
        }
    }
    let sigma = look.noise / region.step as f32 * 6f32.sqrt();
    let gamma = gamma_table();
    let mut image = RgbImage::new(region.w, region.h);
    for (k, (px, c)) in image.pixels_mut().zip(&lin).enumerate() {
        let (j, i) = ((k % w) as i64, (k / w) as i64);
        let (x, y) = (region.x0 + j * region.step as i64, region.y0 + i * region.step as i64);
        let hsh = hash(&[look.seed, x as u64, y as u64]);
        for (ch, &value) in c.iter().enumerate() {
            let lin = (value * look.exposure).clamp(0.0, 1.0);
            let v = gamma[(lin.sqrt() * (GAMMA_STEPS - 1) as f32) as usize];
            let h = hsh.rotate_left(21 * ch as u32);
            // Triangular noise from two 16-bit uniforms of the pixel's hash.
            let nz = (((h & 0xffff) + ((h >> 16) & 0xffff)) as f32 / 65535.0 - 1.0) * sigma;
            px.0[ch] = (v + nz + 0.5).clamp(0.0, 255.0) as u8;
        }
    }
    Rendered { image, ids, region }
}
