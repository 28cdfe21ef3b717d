//! A procedural stand-in body for the glb: one capsule (a tapered cylinder with
//! hemispherical ends) per bone of the rest skeleton, a sphere for the head, each vertex
//! bound to a single joint so it follows the skeleton rigidly.
//!
//! Why procedural: SMPL-X's own mesh is under a licence we cannot ship, and the bundle
//! carries only joints. A capsule from joint `p` to its child `j` is rigid with `p`'s
//! frame (both of its end points move with `p`), so binding it to `p` with weight 1 is
//! exact, not an approximation.
use std::f64::consts::{FRAC_PI_2, TAU};

/// A mesh in the bind pose (= the rest skeleton with every rotation identity).
#[derive(Default)]
pub struct SkinnedMesh {
    pub positions: Vec<[f32; 3]>,
    /// Unit outward normals.
    pub normals: Vec<[f32; 3]>,
    /// The one joint each vertex is bound to (weight 1).
    pub joints: Vec<u8>,
    /// Triangles, counter-clockwise seen from outside.
    pub indices: Vec<u32>,
}

const PELVIS: usize = 0;
const NECK: usize = 12;
const HEAD: usize = 15;
/// Jaw and eyes sit inside the head sphere; no bones for them.
const FACE: [usize; 3] = [22, 23, 24];
/// First finger joint of the left hand; each hand has 5 fingers × 3 joints up to 54.
const FIRST_FINGER: usize = 25;

/// Radii (metres) at the parent and at the child end of the bone ending in joint `j`.
fn bone_radii(j: usize) -> (f64, f64) {
    match j {
        1 | 2 => (0.065, 0.065),   // pelvis → hips
        3 => (0.09, 0.085),        // pelvis → spine1
        4 | 5 => (0.065, 0.048),   // thighs
        6 => (0.09, 0.095),        // spine1 → spine2
        7 | 8 => (0.048, 0.035),   // shins
        9 => (0.095, 0.1),         // spine2 → spine3
        10 | 11 => (0.035, 0.03),  // feet
        12 => (0.06, 0.045),       // spine3 → neck
        13 | 14 => (0.05, 0.05),   // collars
        15 => (0.045, 0.045),      // neck → head
        16 | 17 => (0.05, 0.045),  // collar → shoulder
        18 | 19 => (0.045, 0.037), // upper arms
        20 | 21 => (0.035, 0.027), // forearms
        _ => match (j - FIRST_FINGER) % 3 {
            0 => (0.014, 0.011),   // wrist → finger base: the palm
            1 => (0.0095, 0.0085), // proximal phalanx
            _ => (0.0085, 0.0075), // middle phalanx
        },
    }
}

/// Builds the body for a rest skeleton given in the output basis; `unit` is metres → output
/// units (1, or 100 for centimetres) so the radii scale with the skeleton.
pub fn build(rest: &[[f32; 3]], parents: &[i32], unit: f64) -> SkinnedMesh {
    let rest: Vec<[f64; 3]> = rest.iter().map(|p| p.map(f64::from)).collect();
    let mut m = SkinnedMesh::default();
    for j in 1..rest.len() {
        if FACE.contains(&j) {
            continue;
        }
        let p = parents[j] as usize;
        let (r0, r1) = bone_radii(j);
        let fine = j >= FIRST_FINGER;
        capsule(&mut m, rest[p], rest[j], r0 * unit, r1 * unit, p, fine);
        // SMPL-X has no fingertip joints: extend the last phalanx beyond its joint.
        if fine && (j - FIRST_FINGER) % 3 == 2 {
            let d = sub(rest[j], rest[p]);
            let tip = [rest[j][0] + 0.8 * d[0], rest[j][1] + 0.8 * d[1], rest[j][2] + 0.8 * d[2]];
            capsule(&mut m, rest[j], tip, 0.0075 * unit, 0.0065 * unit, j, true);
        }
    }
    // The head joint is at the base of the skull: the skull's centre lies ~9 cm further
    // along the neck → head direction.
    if rest.len() > HEAD {
        let up = normalize(sub(rest[HEAD], rest[NECK])).unwrap_or([0.0, 1.0, 0.0]);
        let c = [
            rest[HEAD][0] + 0.09 * unit * up[0],
            rest[HEAD][1] + 0.09 * unit * up[1],
            rest[HEAD][2] + 0.09 * unit * up[2],
        ];
        capsule(&mut m, c, c, 0.1 * unit, 0.1 * unit, HEAD, false);
    }
    debug_assert!(m.joints.iter().all(|&j| (j as usize) < rest.len()) && rest.len() > PELVIS);
    m
}

/// Appends a capsule from `a` (radius `r0`) to `b` (radius `r1`) bound to `joint`;
/// `a == b` gives a sphere. `fine`: fewer segments (fingers are small on screen).
fn capsule(m: &mut SkinnedMesh, a: [f64; 3], b: [f64; 3], r0: f64, r1: f64, joint: usize, fine: bool) {
    let (sides, cap_rings) = if fine { (6, 2) } else { (10, 3) };
    let d = sub(b, a);
    let len = norm(d);
    let u = normalize(d).filter(|_| len > 1e-9).unwrap_or([0.0, 1.0, 0.0]);
    // (e1, e2, u) right-handed, so increasing ring angle runs counter-clockwise about u.
    let helper = if u[0].abs() < 0.9 { [1.0, 0.0, 0.0] } else { [0.0, 1.0, 0.0] };
    let e1 = normalize(cross(helper, u)).expect("helper is not parallel to u");
    let e2 = cross(u, e1);

    let base = m.positions.len() as u32;
    let push =
        |m: &mut SkinnedMesh, centre: [f64; 3], along: f64, radius: f64, n_axial: f64, n_radial: f64, phi: f64| {
            let radial = [
                phi.cos() * e1[0] + phi.sin() * e2[0],
                phi.cos() * e1[1] + phi.sin() * e2[1],
                phi.cos() * e1[2] + phi.sin() * e2[2],
            ];
            let pos: [f64; 3] = std::array::from_fn(|k| centre[k] + along * u[k] + radius * radial[k]);
            let n: [f64; 3] = std::array::from_fn(|k| n_axial * u[k] + n_radial * radial[k]);
            m.positions.push(pos.map(|v| v as f32));
            m.normals.push(normalize(n).unwrap_or(u).map(|v| v as f32));
            m.joints.push(joint as u8);
        };
    // Rings from the `a` end to the `b` end: the `a` hemisphere up to its equator, then
    // the `b` hemisphere from its equator on (the taper joins the two equators). Each
    // ring: (centre, offset along u, radius, polar angle θ from the axis).
    let mut rings = Vec::with_capacity(2 * cap_rings);
    for k in 1..=cap_rings {
        let t = FRAC_PI_2 * k as f64 / cap_rings as f64; // from the pole to the equator
        rings.push((a, -r0 * t.cos(), r0 * t.sin(), -t.cos(), t.sin()));
    }
    // A sphere (a == b) has one equator, not two coinciding ones joined by a band of
    // zero-area triangles.
    let first_b = usize::from(len <= 1e-9);
    for k in first_b..cap_rings {
        let t = FRAC_PI_2 * (cap_rings - k) as f64 / cap_rings as f64; // equator → pole
        rings.push((b, r1 * t.cos(), r1 * t.sin(), t.cos(), t.sin()));
    }
    for &(centre, along, radius, na, nr) in &rings {
        for i in 0..sides {
            push(m, centre, along, radius, na, nr, TAU * i as f64 / sides as f64);
        }
    }
    let pole_a = m.positions.len() as u32;
    push(m, a, -r0, 0.0, -1.0, 0.0, 0.0);
    let pole_b = pole_a + 1;
    push(m, b, r1, 0.0, 1.0, 0.0, 0.0);

    let s = sides as u32;
    let at = |ring: usize, i: u32| base + ring as u32 * s + i % s;
    for i in 0..s {
        m.indices.extend([pole_a, at(0, i + 1), at(0, i)]);
        for r in 0..rings.len() - 1 {
            m.indices.extend([at(r, i), at(r, i + 1), at(r + 1, i + 1)]);
            m.indices.extend([at(r, i), at(r + 1, i + 1), at(r + 1, i)]);
        }
        let last = rings.len() - 1;
        m.indices.extend([pole_b, at(last, i), at(last, i + 1)]);
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

fn norm(a: [f64; 3]) -> f64 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}

fn normalize(a: [f64; 3]) -> Option<[f64; 3]> {
    let n = norm(a);
    (n > 0.0 && n.is_finite()).then(|| [a[0] / n, a[1] / n, a[2] / n])
}

#[cfg(test)]
mod tests {
    use super::*;
    use comgrasp::skeleton::SMPLX_PARENTS;

    /// A made-up rest skeleton: joints spread along a helix (any tree shape works).
    fn rest() -> Vec<[f32; 3]> {
        (0..55).map(|j| [0.1 * (j as f32 * 0.7).sin(), 0.02 * j as f32, 0.1 * (j as f32 * 0.7).cos()]).collect()
    }

    #[test]
    fn closed_outward_unit_normal_mesh_bound_to_parents() {
        let m = build(&rest(), &SMPLX_PARENTS, 1.0);
        let n = m.positions.len();
        assert!(n > 1000 && m.normals.len() == n && m.joints.len() == n);
        assert_eq!(m.indices.len() % 3, 0);
        assert!(m.indices.iter().all(|&i| (i as usize) < n));
        for v in &m.normals {
            let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            assert!((l - 1.0).abs() < 1e-6);
        }
        // Jaw/eyes bind nothing; leaves (fingertips) bind their extension; pelvis binds hips.
        for j in [22u8, 23, 24] {
            assert!(!m.joints.contains(&j));
        }
        assert!(m.joints.contains(&0) && m.joints.contains(&39) && m.joints.contains(&54));
        // Every triangle faces outwards: its geometric normal agrees with the vertex normals.
        let f = |i: u32| m.positions[i as usize].map(f64::from);
        let mut agree = 0;
        for t in m.indices.chunks_exact(3) {
            let g = cross(sub(f(t[1]), f(t[0])), sub(f(t[2]), f(t[0])));
            let vn: f64 = t.iter().map(|&i| (0..3).map(|k| g[k] * m.normals[i as usize][k] as f64).sum::<f64>()).sum();
            agree += usize::from(vn > 0.0);
        }
        assert_eq!(agree, m.indices.len() / 3, "every triangle is wound counter-clockwise from outside");
    }

    #[test]
    fn degenerate_bone_is_a_sphere() {
        let mut m = SkinnedMesh::default();
        capsule(&mut m, [1.0, 2.0, 3.0], [1.0, 2.0, 3.0], 0.5, 0.5, 7, false);
        for p in &m.positions {
            let r = ((p[0] - 1.0).powi(2) + (p[1] - 2.0).powi(2) + (p[2] - 3.0).powi(2)).sqrt();
            assert!((r - 0.5).abs() < 1e-6);
        }
        assert!(m.joints.iter().all(|&j| j == 7));
    }
}
