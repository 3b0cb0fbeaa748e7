//! 4×4 row-major rigid transforms (rotation and translation), as Waymo stores extrinsics and
//! poses.

/// A row-major 4×4 transform.
pub type Mat4 = [[f64; 4]; 4];

/// The transform that changes nothing.
pub const IDENTITY: Mat4 = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];

/// A transform from its 16 row-major values.
pub fn mat4(v: &[f64; 16]) -> Mat4 {
    std::array::from_fn(|r| std::array::from_fn(|c| v[r * 4 + c]))
}

/// `a · b`.
pub fn mul(a: &Mat4, b: &Mat4) -> Mat4 {
    std::array::from_fn(|r| std::array::from_fn(|c| (0..4).map(|k| a[r][k] * b[k][c]).sum()))
}

/// The transformed point.
pub fn apply(m: &Mat4, p: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|r| m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3])
}

/// Inverse of a rigid transform: `[R^T | -R^T t]`.
pub fn rigid_inverse(m: &Mat4) -> Mat4 {
    let mut inv = [[0.0; 4]; 4];
    for r in 0..3 {
        for c in 0..3 {
            inv[r][c] = m[c][r];
        }
        inv[r][3] = -(0..3).map(|c| m[c][r] * m[c][3]).sum::<f64>();
    }
    inv[3][3] = 1.0;
    inv
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rigid_inverse_undoes_the_transform() {
        // 90° about z, then a translation
        let m = mat4(&[0.0, -1.0, 0.0, 1.0, 1.0, 0.0, 0.0, 2.0, 0.0, 0.0, 1.0, 3.0, 0.0, 0.0, 0.0, 1.0]);
        assert_eq!(apply(&m, [1.0, 0.0, 0.0]), [1.0, 3.0, 3.0]);
        assert_eq!(apply(&rigid_inverse(&m), [1.0, 3.0, 3.0]), [1.0, 0.0, 0.0]);
        let id = mul(&rigid_inverse(&m), &m);
        for (r, row) in id.iter().enumerate() {
            for (c, v) in row.iter().enumerate() {
                assert_eq!(*v, if r == c { 1.0 } else { 0.0 });
            }
        }
    }
}
