//! Ray intersection with the simulator's primitives: capsules (limbs, poles), ellipsoids (head,
//! trunk, wheels, crowns), yaw-oriented boxes (cars, buildings, bags) and the ground plane z = 0.

use super::math::{add, cross, dot, madd, norm, normalize, scale, sub, V3};

/// A solid primitive in the vehicle frame (or the body frame before placement).
#[derive(Debug, Clone, Copy)]
pub enum Shape {
    Capsule {
        a: V3,
        b: V3,
        r: f64,
    },
    /// `inv` maps an offset from `c` to unit-sphere coordinates (rows = axis / semi-axis).
    Ellipsoid {
        c: V3,
        axes: [V3; 3],
        semi: [f64; 3],
        inv: [V3; 3],
    },
    /// Box with centre `c`, half sizes `half` along its own x (heading), y, z axes; `cs` is
    /// (cos, sin) of `yaw`, kept because every ray needs it.
    Box {
        c: V3,
        half: V3,
        yaw: f64,
        cs: [f64; 2],
    },
}

impl Shape {
    pub fn capsule(a: V3, b: V3, r: f64) -> Shape {
        Shape::Capsule { a, b, r }
    }

    /// Ellipsoid with orthonormal `axes` and semi-axis lengths `semi`.
    pub fn ellipsoid(c: V3, axes: [V3; 3], semi: [f64; 3]) -> Shape {
        let inv = [scale(axes[0], 1.0 / semi[0]), scale(axes[1], 1.0 / semi[1]), scale(axes[2], 1.0 / semi[2])];
        Shape::Ellipsoid { c, axes, semi, inv }
    }

    /// Axis-aligned (in its own yawed frame) box.
    pub fn cuboid(c: V3, size: V3, yaw: f64) -> Shape {
        Shape::Box { c, half: scale(size, 0.5), yaw, cs: [yaw.cos(), yaw.sin()] }
    }

    /// Rotates about z by `yaw` then translates by `t` (body frame → vehicle frame).
    pub fn placed(&self, yaw: f64, t: V3) -> Shape {
        let p = |v: V3| add(super::math::rot_z(v, yaw), t);
        let r = |v: V3| super::math::rot_z(v, yaw);
        match *self {
            Shape::Capsule { a, b, r: rad } => Shape::capsule(p(a), p(b), rad),
            Shape::Ellipsoid { c, axes, semi, .. } => Shape::ellipsoid(p(c), axes.map(r), semi),
            Shape::Box { c, half, yaw: y0, .. } => Shape::cuboid(p(c), scale(half, 2.0), y0 + yaw),
        }
    }

    /// A sphere containing the shape.
    pub fn bounding_sphere(&self) -> (V3, f64) {
        match *self {
            Shape::Capsule { a, b, r } => (scale(add(a, b), 0.5), 0.5 * norm(sub(b, a)) + r),
            Shape::Ellipsoid { c, semi, .. } => (c, semi[0].max(semi[1]).max(semi[2])),
            Shape::Box { c, half, .. } => (c, norm(half)),
        }
    }

    /// Extent of the shape along a unit direction `u`: (min, max) of `dot(p, u)` over the solid.
    pub fn extent(&self, u: V3) -> (f64, f64) {
        match *self {
            Shape::Capsule { a, b, r } => {
                let (x, y) = (dot(a, u), dot(b, u));
                (x.min(y) - r, x.max(y) + r)
            }
            Shape::Ellipsoid { c, axes, semi, .. } => {
                let h = (0..3).map(|i| (semi[i] * dot(axes[i], u)).powi(2)).sum::<f64>().sqrt();
                (dot(c, u) - h, dot(c, u) + h)
            }
            Shape::Box { c, half, cs: [co, s], .. } => {
                let ax = [[co, s, 0.0], [-s, co, 0.0], [0.0, 0.0, 1.0]];
                let h: f64 = (0..3).map(|i| (half[i] * dot(ax[i], u)).abs()).sum();
                (dot(c, u) - h, dot(c, u) + h)
            }
        }
    }

    /// Points on the surface (silhouette sampling for 2D boxes).
    pub fn surface_samples(&self, out: &mut Vec<V3>) {
        match *self {
            Shape::Capsule { a, b, r } => {
                let ax = normalize(sub(b, a));
                let e1 = super::math::orthogonal([0.0, 0.0, 1.0], ax, [1.0, 0.0, 0.0]);
                let e2 = cross(ax, e1);
                for (end, sgn) in [(a, -1.0), (b, 1.0)] {
                    for i in 0..12 {
                        let ang = i as f64 * std::f64::consts::TAU / 12.0;
                        let ring = add(scale(e1, r * ang.cos()), scale(e2, r * ang.sin()));
                        out.push(add(end, ring));
                        for lat in [0.5f64, 0.87] {
                            let rr = add(scale(ring, (1.0 - lat * lat).sqrt()), scale(ax, sgn * r * lat));
                            out.push(add(end, rr));
                        }
                    }
                    out.push(madd(end, ax, sgn * r));
                }
            }
            Shape::Ellipsoid { c, axes, semi, .. } => {
                for i in 0..8 {
                    let el = -std::f64::consts::FRAC_PI_2 + (i as f64 + 0.5) * std::f64::consts::PI / 8.0;
                    for j in 0..16 {
                        let az = j as f64 * std::f64::consts::TAU / 16.0;
                        let q = [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()];
                        let mut p = c;
                        for k in 0..3 {
                            p = madd(p, axes[k], semi[k] * q[k]);
                        }
                        out.push(p);
                    }
                }
                for s in [-1.0, 1.0] {
                    out.push(madd(c, axes[2], s * semi[2]));
                }
            }
            Shape::Box { c, half, yaw, .. } => {
                for i in 0..8 {
                    let q = [
                        if i & 1 == 0 { -half[0] } else { half[0] },
                        if i & 2 == 0 { -half[1] } else { half[1] },
                        if i & 4 == 0 { -half[2] } else { half[2] },
                    ];
                    out.push(add(c, super::math::rot_z(q, yaw)));
                }
            }
        }
    }

    /// Distance along the unit ray `o + t·d` to the first surface hit with `t > t_min`,
    /// and the outward normal there.
    pub fn intersect(&self, o: V3, d: V3, t_min: f64) -> Option<(f64, V3)> {
        match *self {
            Shape::Capsule { a, b, r } => capsule_hit(o, d, a, b, r, t_min),
            Shape::Ellipsoid { c, inv, .. } => {
                let oc = sub(o, c);
                let qo = [dot(inv[0], oc), dot(inv[1], oc), dot(inv[2], oc)];
                let qd = [dot(inv[0], d), dot(inv[1], d), dot(inv[2], d)];
                let aa = dot(qd, qd);
                let bb = dot(qo, qd);
                let cc = dot(qo, qo) - 1.0;
                let h = bb * bb - aa * cc;
                if h < 0.0 {
                    return None;
                }
                let t = (-bb - h.sqrt()) / aa;
                if t <= t_min {
                    return None;
                }
                let q = madd(qo, qd, t);
                let n = add(add(scale(inv[0], q[0]), scale(inv[1], q[1])), scale(inv[2], q[2]));
                Some((t, normalize(n)))
            }
            Shape::Box { c, half, cs: [co, s], .. } => {
                let oc = sub(o, c);
                let lo = [co * oc[0] + s * oc[1], -s * oc[0] + co * oc[1], oc[2]];
                let ld = [co * d[0] + s * d[1], -s * d[0] + co * d[1], d[2]];
                let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
                let mut axis = 0;
                let mut sign = 1.0;
                for i in 0..3 {
                    if ld[i].abs() < 1e-12 {
                        if lo[i].abs() > half[i] {
                            return None;
                        }
                        continue;
                    }
                    let inv = 1.0 / ld[i];
                    let (mut ta, mut tb) = ((-half[i] - lo[i]) * inv, (half[i] - lo[i]) * inv);
                    let mut sg = -1.0;
                    if ta > tb {
                        std::mem::swap(&mut ta, &mut tb);
                        sg = 1.0;
                    }
                    if ta > t0 {
                        t0 = ta;
                        axis = i;
                        sign = sg;
                    }
                    t1 = t1.min(tb);
                }
                if t0 > t1 || t0 <= t_min {
                    return None;
                }
                let mut ln = [0.0; 3];
                ln[axis] = sign;
                Some((t0, [co * ln[0] - s * ln[1], s * ln[0] + co * ln[1], ln[2]]))
            }
        }
    }
}

fn capsule_hit(o: V3, d: V3, a: V3, b: V3, r: f64, t_min: f64) -> Option<(f64, V3)> {
    let ba = sub(b, a);
    let oa = sub(o, a);
    let baba = dot(ba, ba);
    let bard = dot(ba, d);
    let baoa = dot(ba, oa);
    let rdoa = dot(d, oa);
    let oaoa = dot(oa, oa);
    let aa = baba - bard * bard;
    let normal = |t: f64| {
        let p = madd(o, d, t);
        let pa = sub(p, a);
        let h = (dot(pa, ba) / baba).clamp(0.0, 1.0);
        normalize(sub(pa, scale(ba, h)))
    };
    if aa > 1e-12 {
        let bb = baba * rdoa - baoa * bard;
        let cc = baba * oaoa - baoa * baoa - r * r * baba;
        let h = bb * bb - aa * cc;
        if h < 0.0 {
            return None;
        }
        let t = (-bb - h.sqrt()) / aa;
        let y = baoa + t * bard;
        if y > 0.0 && y < baba {
            return (t > t_min).then(|| (t, normal(t)));
        }
    }
    // The side was missed or hit beyond an end: try the end sphere on the near side.
    let mut best: Option<f64> = None;
    for c in [a, b] {
        let oc = sub(o, c);
        let b2 = dot(d, oc);
        let c2 = dot(oc, oc) - r * r;
        let h2 = b2 * b2 - c2;
        if h2 >= 0.0 {
            let t = -b2 - h2.sqrt();
            if t > t_min && best.is_none_or(|bt| t < bt) {
                best = Some(t);
            }
        }
    }
    best.map(|t| (t, normal(t)))
}

/// Distance to the ground plane z = 0 along the unit ray (downward rays from above only).
#[inline]
pub fn ground_hit(o: V3, d: V3) -> Option<f64> {
    (d[2] < -1e-9 && o[2] > 0.0).then(|| -o[2] / d[2])
}

/// Cheap rejection: can the ray reach the sphere (c, r) before `t_max`?
#[inline]
pub fn ray_may_hit_sphere(o: V3, d: V3, c: V3, r: f64, t_max: f64) -> bool {
    let oc = sub(c, o);
    let b = dot(oc, d);
    if b + r < 0.0 || b - r > t_max {
        return false;
    }
    dot(oc, oc) - b * b <= r * r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn capsule_side_and_cap_hits_match_hand_computed_distances() {
        let c = Shape::capsule([5.0, 0.0, 0.0], [5.0, 0.0, 2.0], 0.5);
        let (t, n) = c.intersect([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], 0.0).unwrap();
        assert!((t - 4.5).abs() < 1e-12 && (n[0] + 1.0).abs() < 1e-12);
        // Straight down onto the top cap.
        let (t, n) = c.intersect([5.0, 0.0, 10.0], [0.0, 0.0, -1.0], 0.0).unwrap();
        assert!((t - 7.5).abs() < 1e-12 && (n[2] - 1.0).abs() < 1e-12);
        assert!(c.intersect([0.0, 0.6, 1.0], [1.0, 0.0, 0.0], 0.0).is_none());
    }

    #[test]
    fn ellipsoid_and_box_hits() {
        let e =
            Shape::ellipsoid([10.0, 0.0, 1.0], [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], [0.2, 0.3, 0.5]);
        let (t, _) = e.intersect([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], 0.0).unwrap();
        assert!((t - 9.8).abs() < 1e-12);
        let (t, _) = e.intersect([10.0, -5.0, 1.0], [0.0, 1.0, 0.0], 0.0).unwrap();
        assert!((t - 4.7).abs() < 1e-12);
        let b = Shape::cuboid([10.0, 0.0, 1.0], [2.0, 1.0, 2.0], std::f64::consts::FRAC_PI_2);
        // Rotated by 90°: the 2 m length now lies along y, so the near face is 0.5 m away in x.
        let (t, n) = b.intersect([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], 0.0).unwrap();
        assert!((t - 9.5).abs() < 1e-12 && (n[0] + 1.0).abs() < 1e-9, "{t} {n:?}");
        let (lo, hi) = b.extent([0.0, 1.0, 0.0]);
        assert!((lo + 1.0).abs() < 1e-12 && (hi - 1.0).abs() < 1e-12);
    }
}
