//! The bundle skeleton (SMPL-X topology, 55 joints) and the rotation math frame assembly
//! needs: 6D → rotation matrix, matrix → quaternion, forward kinematics.
//!
//! Conventions (the Python side: `comgrasp_train.skeleton` / `rotations`):
//! * Matrices are row-major `m[row][col]` and act on column vectors: `v' = R v`.
//! * 6D = the first two ROWS of the matrix (pytorch3d `matrix_to_rotation_6d`).
//! * Forward kinematics follows SMPL-X's joint chain: `G_i = G_parent · R_i`,
//!   `p_i = p_parent + G_parent (J_i − J_parent)`, the root `G_0 = R_0` at the posed
//!   pelvis. (Python writes the root as `[R_0 | J_0]` plus `transl = pelvis − J_0`; the
//!   same positions, here with the pelvis exactly equal to the root translation.)
//!
//! Everything is `f64` internally and allocation-free (fixed-size arrays).

use crate::error::{Error, Result};
use crate::frame::CG_NUM_JOINTS;

pub type Vec3 = [f64; 3];
/// Row-major 3×3 matrix, `m[row][col]`, acting on column vectors.
pub type Mat3 = [[f64; 3]; 3];

pub const IDENTITY: Mat3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// The SMPL-X kinematic tree (parent of each joint, -1 for the pelvis).
pub const SMPLX_PARENTS: [i32; CG_NUM_JOINTS] = [
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15, 20, 25, 26, 20, 28, 29, 20,
    31, 32, 20, 34, 35, 20, 37, 38, 21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53,
];
pub const LEFT_WRIST: usize = 20;
pub const RIGHT_WRIST: usize = 21;

pub fn mat_mul(a: &Mat3, b: &Mat3) -> Mat3 {
    let mut c = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            c[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    c
}

pub fn mat_vec(a: &Mat3, v: &Vec3) -> Vec3 {
    [
        a[0][0] * v[0] + a[0][1] * v[1] + a[0][2] * v[2],
        a[1][0] * v[0] + a[1][1] * v[1] + a[1][2] * v[2],
        a[2][0] * v[0] + a[2][1] * v[1] + a[2][2] * v[2],
    ]
}

pub fn transpose(a: &Mat3) -> Mat3 {
    [[a[0][0], a[1][0], a[2][0]], [a[0][1], a[1][1], a[2][1]], [a[0][2], a[1][2], a[2][2]]]
}

pub fn det(a: &Mat3) -> f64 {
    a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1]) - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
        + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0])
}

pub fn dot(a: &Vec3, b: &Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub fn cross(a: &Vec3, b: &Vec3) -> Vec3 {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

pub fn add(a: &Vec3, b: &Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

pub fn sub(a: &Vec3, b: &Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub fn scale(a: &Vec3, k: f64) -> Vec3 {
    [a[0] * k, a[1] * k, a[2] * k]
}

pub fn norm(a: &Vec3) -> f64 {
    dot(a, a).sqrt()
}

/// Rotation by `angle` radians about the unit `axis` (Rodrigues).
pub fn axis_angle(axis: &Vec3, angle: f64) -> Mat3 {
    let (s, c) = angle.sin_cos();
    let t = 1.0 - c;
    let [x, y, z] = *axis;
    [
        [t * x * x + c, t * x * y - s * z, t * x * z + s * y],
        [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
        [t * x * z - s * y, t * y * z + s * x, t * z * z + c],
    ]
}

/// A unit vector orthogonal to the unit `v`.
pub fn orthogonal(v: &Vec3) -> Vec3 {
    let i = (0..3).min_by(|&i, &j| v[i].abs().total_cmp(&v[j].abs())).unwrap_or(0);
    let mut e = [0.0; 3];
    e[i] = 1.0;
    let c = cross(v, &e);
    let n = norm(&c);
    [c[0] / n, c[1] / n, c[2] / n]
}

/// The smallest rotation turning the direction of `a` into the direction of `b` (identity
/// when either is zero).
pub fn rotation_between(a: &Vec3, b: &Vec3) -> Mat3 {
    let (na, nb) = (norm(a), norm(b));
    if !(na > NORM_EPS && nb > NORM_EPS) {
        return IDENTITY;
    }
    let (a, b) = (scale(a, 1.0 / na), scale(b, 1.0 / nb));
    let axis = cross(&a, &b);
    let s = norm(&axis);
    let c = dot(&a, &b);
    if s > 1e-12 {
        axis_angle(&scale(&axis, 1.0 / s), s.atan2(c))
    } else if c > 0.0 {
        IDENTITY
    } else {
        axis_angle(&orthogonal(&a), std::f64::consts::PI)
    }
}

/// Below this norm a 6D column is degenerate (torch `F.normalize`'s eps).
const NORM_EPS: f64 = 1e-12;

/// 6D (first two rows, row-major) → rotation matrix by Gram–Schmidt, as pytorch3d's
/// `rotation_6d_to_matrix`: `b1 = a1/|a1|`, `b2 = normalize(a2 − (b1·a2) b1)`,
/// `b3 = b1 × b2`, rows `(b1, b2, b3)`.
///
/// Why the extra branches: the network's 6D is not exactly orthonormal and could in
/// principle be degenerate (a zero row, two parallel rows) or non-finite, where Python
/// returns a non-rotation. A host must never receive a NaN or non-unit quaternion, so a
/// degenerate `a1` falls back to the x axis and a degenerate residual `a2` to a vector
/// orthogonal to `b1`. The result is always a proper rotation (det +1).
pub fn rot6d_to_matrix(d: &[f64; 6]) -> Mat3 {
    let a1 = [d[0], d[1], d[2]];
    let a2 = [d[3], d[4], d[5]];
    let n1 = dot(&a1, &a1).sqrt();
    let b1 = if n1 > NORM_EPS && n1.is_finite() { [a1[0] / n1, a1[1] / n1, a1[2] / n1] } else { [1.0, 0.0, 0.0] };
    let a2 = if a2.iter().all(|v| v.is_finite()) { a2 } else { [0.0; 3] };
    let p = dot(&b1, &a2);
    let r = [a2[0] - p * b1[0], a2[1] - p * b1[1], a2[2] - p * b1[2]];
    let n2 = dot(&r, &r).sqrt();
    let b2 = if n2 > NORM_EPS && n2.is_finite() { [r[0] / n2, r[1] / n2, r[2] / n2] } else { orthogonal(&b1) };
    let b3 = cross(&b1, &b2);
    [b1, b2, b3]
}

/// Rotation matrix → unit quaternion `[x, y, z, w]` with `w >= 0`.
///
/// Shepperd's method, as `comgrasp_train.rotations.matrix_to_quaternion`: of the four
/// algebraically equivalent formulas take the one with the largest denominator (|w|,
/// |x|, |y| or |z| largest), which is accurate for every rotation including 180° ones;
/// then normalize and flip to `w >= 0` (q and −q are the same rotation; hosts get a
/// canonical one).
pub fn matrix_to_quaternion(m: &Mat3) -> [f64; 4] {
    let (m00, m01, m02) = (m[0][0], m[0][1], m[0][2]);
    let (m10, m11, m12) = (m[1][0], m[1][1], m[1][2]);
    let (m20, m21, m22) = (m[2][0], m[2][1], m[2][2]);
    let t = [
        1.0 + m00 + m11 + m22, // 4 w²
        1.0 + m00 - m11 - m22, // 4 x²
        1.0 - m00 + m11 - m22, // 4 y²
        1.0 - m00 - m11 + m22, // 4 z²
    ];
    let mut best = 0;
    for i in 1..4 {
        if t[i] > t[best] {
            best = i;
        }
    }
    let s = t[best].max(0.0).sqrt(); // 2 |q_best|
    let s = if s > 0.0 { s } else { 1.0 };
    // (w, x, y, z) * 2 s
    let (w, x, y, z) = match best {
        0 => (s * s, m21 - m12, m02 - m20, m10 - m01),
        1 => (m21 - m12, s * s, m10 + m01, m02 + m20),
        2 => (m02 - m20, m10 + m01, s * s, m12 + m21),
        _ => (m10 - m01, m20 + m02, m21 + m12, s * s),
    };
    let n = (w * w + x * x + y * y + z * z).sqrt();
    if n.is_nan() || n <= 0.0 || n.is_infinite() {
        return [0.0, 0.0, 0.0, 1.0];
    }
    let sign = if w < 0.0 { -1.0 } else { 1.0 };
    let k = sign / n;
    [x * k, y * k, z * k, w * k]
}

/// Unit quaternion `[x, y, z, w]` → rotation matrix (for tests and hosts' reference).
pub fn quaternion_to_matrix(q: &[f64; 4]) -> Mat3 {
    let [x, y, z, w] = *q;
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
        [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
        [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

/// The bundle's skeleton: SMPL-X topology (55 joints), rest joint positions from the
/// manifest (metres, SMPL-X canonical rest frame: y up, +z forward, subject's left +x).
#[derive(Clone, Debug, PartialEq)]
pub struct Skeleton {
    parents: [i32; CG_NUM_JOINTS],
    rest: [Vec3; CG_NUM_JOINTS],
    /// `J_i − J_parent` (the root's is `J_0`, unused).
    offsets: [Vec3; CG_NUM_JOINTS],
}

impl Skeleton {
    /// Validates the manifest's tree: 55 joints, joint 0 the only root, every parent
    /// listed before its child (so one pass in index order is a valid FK order), finite
    /// rest positions. Errors are [`Error::InvalidArgument`] (the loader adds the path).
    pub fn new(parents: &[i32], rest_joints: &[[f32; 3]]) -> Result<Self> {
        let n = CG_NUM_JOINTS;
        if parents.len() != n || rest_joints.len() != n {
            return Err(Error::InvalidArgument(format!(
                "skeleton: expected {n} joints, got {} parents and {} rest joints",
                parents.len(),
                rest_joints.len()
            )));
        }
        if parents[0] != -1 {
            return Err(Error::InvalidArgument(format!(
                "skeleton: joint 0 must be the root (parent -1), got {}",
                parents[0]
            )));
        }
        for (j, &p) in parents.iter().enumerate().skip(1) {
            if p < 0 || p as usize >= j {
                return Err(Error::InvalidArgument(format!(
                    "skeleton: joint {j} has parent {p}; parents must precede their children"
                )));
            }
        }
        if let Some(j) = rest_joints.iter().position(|r| r.iter().any(|v| !v.is_finite())) {
            return Err(Error::InvalidArgument(format!("skeleton: rest joint {j} is not finite")));
        }
        let mut s = Skeleton {
            parents: [0; CG_NUM_JOINTS],
            rest: [[0.0; 3]; CG_NUM_JOINTS],
            offsets: [[0.0; 3]; CG_NUM_JOINTS],
        };
        s.parents.copy_from_slice(parents);
        for (r, j) in s.rest.iter_mut().zip(rest_joints) {
            *r = j.map(f64::from);
        }
        s.offsets[0] = s.rest[0];
        for (j, &p) in parents.iter().enumerate().skip(1) {
            let (c, p) = (s.rest[j], s.rest[p as usize]);
            s.offsets[j] = [c[0] - p[0], c[1] - p[1], c[2] - p[2]];
        }
        Ok(s)
    }

    pub fn parents(&self) -> &[i32; CG_NUM_JOINTS] {
        &self.parents
    }

    /// Rest joint positions (metres, the manifest's frame).
    pub fn rest_joints(&self) -> &[Vec3; CG_NUM_JOINTS] {
        &self.rest
    }

    /// Forward kinematics. `local[0]` is the root's global rotation, `local[i]` the
    /// other joints' rotations relative to their parent; `pelvis` is the posed root
    /// position. Writes global rotations and world positions. No allocation.
    pub fn forward(
        &self,
        local: &[Mat3; CG_NUM_JOINTS],
        pelvis: Vec3,
        global: &mut [Mat3; CG_NUM_JOINTS],
        positions: &mut [Vec3; CG_NUM_JOINTS],
    ) {
        global[0] = local[0];
        positions[0] = pelvis;
        for j in 1..CG_NUM_JOINTS {
            let p = self.parents[j] as usize;
            let o = mat_vec(&global[p], &self.offsets[j]);
            positions[j] = [positions[p][0] + o[0], positions[p][1] + o[1], positions[p][2] + o[2]];
            global[j] = mat_mul(&global[p], &local[j]);
        }
    }
}

/// The angle of rotation `r` (radians, 0 to π).
pub fn rotation_angle(r: &Mat3) -> f64 {
    let q = matrix_to_quaternion(r);
    2.0 * norm(&[q[0], q[1], q[2]]).atan2(q[3].abs())
}

/// `r` turned back toward the identity by at most `step` radians.
pub fn fade_rotation(r: &Mat3, step: f64) -> Mat3 {
    if *r == IDENTITY {
        return IDENTITY;
    }
    let q = matrix_to_quaternion(r);
    let v = norm(&[q[0], q[1], q[2]]);
    let angle = 2.0 * v.atan2(q[3].abs());
    if angle <= step || v <= 1e-12 {
        return IDENTITY;
    }
    let sign = if q[3] < 0.0 { -1.0 } else { 1.0 };
    axis_angle(&[sign * q[0] / v, sign * q[1] / v, sign * q[2] / v], angle - step)
}

/// Two-bone IK on the limb `[parent, root, middle, end]` (collar, shoulder, elbow, wrist;
/// pelvis, hip, knee, ankle): turns the middle joint, then the root, so the end lands on
/// `target` (or as near as the slightly bent limb reaches), and gives the end the global
/// rotation `end` (the hand's or the foot's orientation; its children are local to it).
/// The middle joint bends in the limb's own plane, so an elbow or a knee keeps the side it
/// bends to. `global` / `joints` are the pose's FK before the change; `local` is rewritten
/// for the root, middle and end only.
pub fn limb_ik(
    local: &mut [Mat3; CG_NUM_JOINTS],
    global: &[Mat3; CG_NUM_JOINTS],
    joints: &[Vec3; CG_NUM_JOINTS],
    limb: [usize; 4],
    target: &Vec3,
    end: &Mat3,
) {
    let [c, s, e, w] = limb;
    let (ps, pe, pw) = (joints[s], joints[e], joints[w]);
    let u = sub(&pe, &ps);
    let f = sub(&pw, &pe);
    let (a, b) = (norm(&u), norm(&f));
    if !(a > 1e-6 && b > 1e-6 && target.iter().all(|v| v.is_finite())) {
        return;
    }
    // Bend: the angle β between the upper and lower bone (0 = straight) sets |end - root|.
    let lo = (a - b).abs() + 1e-4;
    let hi = (a + b) * 0.999;
    let d = norm(&sub(target, &ps)).clamp(lo, hi);
    let mut axis = cross(&u, &f);
    let n = norm(&axis);
    axis = if n > 1e-9 * a * b {
        scale(&axis, 1.0 / n)
    } else {
        // A straight limb bends about an axis orthogonal to it and to the target.
        let t = cross(&u, &sub(target, &ps));
        if norm(&t) > 1e-9 {
            scale(&t, 1.0 / norm(&t))
        } else {
            orthogonal(&scale(&u, 1.0 / a))
        }
    };
    let beta = norm(&cross(&u, &f)).atan2(dot(&u, &f));
    let cos_new = ((d * d - a * a - b * b) / (2.0 * a * b)).clamp(-1.0, 1.0);
    let bend = axis_angle(&axis, cos_new.acos() - beta);
    let end1 = add(&pe, &mat_vec(&bend, &f));
    // Swing: the smallest root rotation that points root→end at the target.
    let swing = rotation_between(&sub(&end1, &ps), &sub(target, &ps));
    let gs = mat_mul(&swing, &global[s]);
    let ge = mat_mul(&swing, &mat_mul(&bend, &global[e]));
    local[s] = mat_mul(&transpose(&global[c]), &gs);
    local[e] = mat_mul(&transpose(&gs), &ge);
    local[w] = mat_mul(&transpose(&ge), end);
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::sampler::SplitMix64;

    /// A random rotation from a seeded RNG (uniform quaternion by normalizing a Gaussian-ish
    /// 4-vector; the distribution does not matter here).
    pub(crate) fn random_rotation(r: &mut SplitMix64) -> Mat3 {
        loop {
            let q: [f64; 4] = std::array::from_fn(|_| r.next_uniform() * 2.0 - 1.0);
            let n = (q.iter().map(|v| v * v).sum::<f64>()).sqrt();
            if n > 0.1 && n <= 1.0 {
                return quaternion_to_matrix(&q.map(|v| v / n));
            }
        }
    }

    fn max_abs_diff(a: &Mat3, b: &Mat3) -> f64 {
        let mut m = 0.0f64;
        for i in 0..3 {
            for j in 0..3 {
                m = m.max((a[i][j] - b[i][j]).abs());
            }
        }
        m
    }

    fn to6d(m: &Mat3) -> [f64; 6] {
        [m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2]]
    }

    #[test]
    fn rot6d_and_quaternion_round_trip() {
        let mut r = SplitMix64::new(11);
        for _ in 0..2000 {
            let m = random_rotation(&mut r);
            let back = rot6d_to_matrix(&to6d(&m));
            assert!(max_abs_diff(&m, &back) < 1e-12);
            let q = matrix_to_quaternion(&m);
            assert!(q[3] >= 0.0);
            assert!((q.iter().map(|v| v * v).sum::<f64>() - 1.0).abs() < 1e-12);
            assert!(max_abs_diff(&m, &quaternion_to_matrix(&q)) < 1e-12);
        }
        // Non-orthonormal 6D (scaled, skewed rows) still gives the Gram-Schmidt rotation.
        let m = random_rotation(&mut r);
        let mut d = to6d(&m);
        for v in d.iter_mut().take(3) {
            *v *= 3.0;
        }
        for i in 0..3 {
            d[3 + i] = 0.5 * d[3 + i] + 0.7 * d[i];
        }
        assert!(max_abs_diff(&m, &rot6d_to_matrix(&d)) < 1e-12);
    }

    #[test]
    fn quaternion_edge_cases() {
        // 180° rotations about each axis and about a diagonal: the w ≈ 0 branch.
        let cases: [(Mat3, [f64; 4]); 3] = [
            ([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]], [1.0, 0.0, 0.0, 0.0]),
            ([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]], [0.0, 1.0, 0.0, 0.0]),
            ([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]], [0.0, 0.0, 1.0, 0.0]),
        ];
        for (m, q) in cases {
            assert_eq!(matrix_to_quaternion(&m), q);
        }
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let q = matrix_to_quaternion(&quaternion_to_matrix(&[h, h, 0.0, 0.0]));
        assert!((q[0] - h).abs() < 1e-15 && (q[1] - h).abs() < 1e-15);
        assert_eq!(matrix_to_quaternion(&IDENTITY), [0.0, 0.0, 0.0, 1.0]);
    }

    #[test]
    fn rot6d_matches_python_quaternions() {
        // comgrasp_train.rotations.matrix_to_quaternion(rotation_6d_to_matrix(d)) in
        // Python, (w, x, y, z), for hand-picked non-orthonormal 6D inputs.
        let cases: [([f64; 6], [f64; 4]); 4] = [
            (
                [0.9, 0.1, -0.2, 0.05, 1.1, 0.3],
                [0.9827216960899975, -0.139662262080605, -0.1151991683956569, -0.03849249518381755],
            ),
            (
                [-0.3, 0.8, 0.4, 0.9, 0.2, -0.1],
                [0.18942376384884746, 0.5523757377803465, 0.8045875254196532, 0.1078823245023622],
            ),
            (
                [0.0, 0.0, 2.0, 1.0, 1.0, 0.0],
                [0.6532814824381884, 0.2705980500730985, 0.6532814824381883, 0.2705980500730985],
            ),
            (
                [0.2, -0.9, 0.1, -0.6, -0.1, 0.7],
                [0.3539194378504431, -0.6946753232374567, 0.585969566881027, 0.220922822464822],
            ),
        ];
        for (d, wxyz) in cases {
            let q = matrix_to_quaternion(&rot6d_to_matrix(&d));
            let want = [wxyz[1], wxyz[2], wxyz[3], wxyz[0]];
            for i in 0..4 {
                assert!((q[i] - want[i]).abs() < 1e-12, "{d:?}: {q:?} vs {want:?}");
            }
        }
    }

    #[test]
    fn degenerate_6d_gives_a_rotation() {
        for d in [
            [0.0; 6],
            [1.0, 0.0, 0.0, 2.0, 0.0, 0.0],
            [f64::NAN, 0.0, 0.0, 0.0, 1.0, 0.0],
            [0.0, 1.0, 0.0, f64::INFINITY, 0.0, 0.0],
        ] {
            let m = rot6d_to_matrix(&d);
            assert!((det(&m) - 1.0).abs() < 1e-12, "{d:?}");
            assert!(max_abs_diff(&mat_mul(&m, &transpose(&m)), &IDENTITY) < 1e-12);
        }
    }

    #[test]
    fn skeleton_validation() {
        let rest = [[0.0f32; 3]; 55];
        assert!(Skeleton::new(&SMPLX_PARENTS, &rest).is_ok());
        assert!(Skeleton::new(&SMPLX_PARENTS[..54], &rest[..54]).is_err());
        let mut bad = SMPLX_PARENTS;
        bad[5] = 7;
        assert!(Skeleton::new(&bad, &rest).is_err());
        let mut bad = SMPLX_PARENTS;
        bad[0] = 0;
        assert!(Skeleton::new(&bad, &rest).is_err());
        let mut r = rest;
        r[3][1] = f32::NAN;
        assert!(Skeleton::new(&SMPLX_PARENTS, &r).is_err());
    }

    #[test]
    fn fk_identity_pose_is_the_rest_pose_moved_to_the_pelvis() {
        let rest: Vec<[f32; 3]> =
            (0..55).map(|j| [j as f32 * 0.01, (j % 7) as f32 * 0.1, -(j as f32) * 0.02]).collect();
        let sk = Skeleton::new(&SMPLX_PARENTS, &rest).unwrap();
        let local = [IDENTITY; 55];
        let (mut g, mut p) = ([IDENTITY; 55], [[0.0; 3]; 55]);
        sk.forward(&local, [1.0, 2.0, 3.0], &mut g, &mut p);
        for j in 0..55 {
            for a in 0..3 {
                let want = rest[j][a] as f64 - rest[0][a] as f64 + [1.0, 2.0, 3.0][a];
                assert!((p[j][a] - want).abs() < 1e-12);
            }
        }
    }
}
