//! BVH (Biovision hierarchy) export for animation tools (Blender, MotionBuilder, retargeting
//! tools): the SMPL-X skeleton with fingers, one frame per engine frame at the bundle's fps.
//!
//! Conventions, as most tools read BVH: y up, centimetres (the glTF basis × 100), every
//! joint `CHANNELS 3 Zrotation Xrotation Yrotation` (the local rotation is `Rz · Rx · Ry`,
//! degrees), the root (`pelvis`) also `Xposition Yposition Zposition` first, with a zero
//! OFFSET so its channels are its world position. The rest pose is the bundle's skeleton in
//! its own frame (SMPL-X's: y up, facing +z, T-pose), so a tool shows it standing; the
//! root's rotation carries the turn from that frame into the world. Leaves end in an
//! `End Site` 5 cm along their parent's bone. The object is a second file (`<name>.object.bvh`): one root joint
//! `object` with the object's origin and rotation per frame (a single-root file, which
//! every BVH reader takes).
//!
//! Frames in any coordinate system are taken (the engine's: its frames carry `S R S^T` and
//! `c S p` for the native `R` and `p`, see `assemble`); the file is always the y-up one above.
//! Used by `comgrasp generate --bvh`, [`crate::engine::Engine::write_bvh`] and the C ABI's
//! `cg_engine_write_bvh` (the Python binding's `Engine.write_bvh`).
use std::fmt::Write as _;

use crate::error::{Error, Result};
use crate::frame::{CoordinateSystem, Frame, CG_BODY_JOINTS, CG_HAND_JOINTS, CG_NUM_JOINTS};
use crate::retarget::SMPLX_JOINT_NAMES;
use crate::skeleton::{mat_mul, mat_vec, quaternion_to_matrix, transpose, Mat3, Vec3, SMPLX_PARENTS};

/// Centimetres per metre.
const CM: f64 = 100.0;

/// Euler angles (degrees) of `r = Rz(z) · Rx(x) · Ry(y)`, as (z, x, y).
pub fn zxy_degrees(r: &Mat3) -> [f64; 3] {
    let x = r[2][1].clamp(-1.0, 1.0).asin();
    let (z, y) = if x.cos() > 1e-9 {
        ((-r[0][1]).atan2(r[1][1]), (-r[2][0]).atan2(r[2][2]))
    } else {
        // Gimbal lock (x = ±90°): only z ± y is defined; put it all in z.
        (r[1][0].atan2(r[0][0]), 0.0)
    };
    [z.to_degrees(), x.to_degrees(), y.to_degrees()]
}

fn local_rotations(f: &Frame) -> [[f32; 4]; CG_NUM_JOINTS] {
    let mut q = [[0.0, 0.0, 0.0, 1.0]; CG_NUM_JOINTS];
    q[0] = f.root_rotation;
    q[1..=CG_BODY_JOINTS].copy_from_slice(&f.body_rotations);
    q[25..25 + CG_HAND_JOINTS].copy_from_slice(&f.left_hand_rotations);
    q[40..40 + CG_HAND_JOINTS].copy_from_slice(&f.right_hand_rotations);
    q
}

fn children(j: usize) -> impl Iterator<Item = usize> {
    (j + 1..CG_NUM_JOINTS).filter(move |&c| SMPLX_PARENTS[c] == j as i32)
}

fn hierarchy(out: &mut String, rest: &[[f32; 3]; CG_NUM_JOINTS], j: usize, depth: usize) {
    let pad = "  ".repeat(depth);
    let p = SMPLX_PARENTS[j];
    let offset =
        if p < 0 { [0.0; 3] } else { std::array::from_fn(|i| f64::from(rest[j][i] - rest[p as usize][i]) * CM) };
    let kind = if p < 0 { "ROOT" } else { "JOINT" };
    let _ = writeln!(out, "{pad}{kind} {}\n{pad}{{", SMPLX_JOINT_NAMES[j]);
    let _ = writeln!(out, "{pad}  OFFSET {:.6} {:.6} {:.6}", offset[0], offset[1], offset[2]);
    let channels = if p < 0 {
        "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"
    } else {
        "CHANNELS 3 Zrotation Xrotation Yrotation"
    };
    let _ = writeln!(out, "{pad}  {channels}");
    let mut any = false;
    for c in children(j) {
        hierarchy(out, rest, c, depth + 1);
        any = true;
    }
    if !any {
        // An end site 5 cm on along the bone into this joint (or up, for a lone root).
        let d: [f64; 3] = if p < 0 { [0.0, 1.0, 0.0] } else { std::array::from_fn(|i| offset[i]) };
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-9);
        let e = d.map(|v| v / n * 5.0);
        let _ =
            writeln!(out, "{pad}  End Site\n{pad}  {{\n{pad}    OFFSET {:.6} {:.6} {:.6}\n{pad}  }}", e[0], e[1], e[2]);
    }
    let _ = writeln!(out, "{pad}}}");
}

fn motion_header(out: &mut String, frames: usize, fps: f64) {
    let _ = writeln!(out, "MOTION\nFrames: {frames}\nFrame Time: {:.8}", 1.0 / fps);
}

fn push_rotation(line: &mut String, r: &Mat3) {
    let e = zxy_degrees(r);
    let _ = write!(line, " {:.6} {:.6} {:.6}", e[0], e[1], e[2]);
}

/// Frames of one coordinate system mapped into the file's (y up, centimetres).
struct ToFile {
    coords: CoordinateSystem,
    /// glTF's basis: the file's axes.
    g: Mat3,
    gt: Mat3,
}

impl ToFile {
    fn new(coords: CoordinateSystem) -> Self {
        let (g, _) = CoordinateSystem::CG_COORDS_GLTF.basis();
        ToFile { coords, g, gt: transpose(&g) }
    }

    /// A frame's rotation as the native one.
    fn native(&self, q: &[f32; 4]) -> Mat3 {
        self.coords.to_native_rotation(&quaternion_to_matrix(&q.map(f64::from)))
    }

    /// A frame's point in the file, centimetres.
    fn point(&self, p: &[f32; 3]) -> Vec3 {
        mat_vec(&self.g, &self.coords.to_native_point(&p.map(f64::from))).map(|v| v * CM)
    }
}

/// Fails on a frame with a non-finite value (a file of NaNs would load as garbage), or an
/// fps that is not positive.
fn check(frames: &[Frame], fps: f64) -> Result<()> {
    if !(fps.is_finite() && fps > 0.0) {
        return Err(Error::InvalidArgument(format!("fps {fps} is not positive")));
    }
    for (i, f) in frames.iter().enumerate() {
        let values = f.root_translation.iter().chain(&f.root_rotation).chain(f.body_rotations.iter().flatten());
        let values =
            values.chain(f.left_hand_rotations.iter().flatten()).chain(f.right_hand_rotations.iter().flatten());
        if !values.chain(&f.object_translation).chain(&f.object_rotation).all(|v| v.is_finite()) {
            return Err(Error::InvalidArgument(format!("frame {i} has a non-finite value: no BVH written")));
        }
    }
    Ok(())
}

/// The body: `rest` the bundle's rest joints (the manifest's, in the skeleton's own frame),
/// `frames` in `coords` (an engine's frames: its coordinate system).
pub fn body(rest: &[[f32; 3]; CG_NUM_JOINTS], frames: &[Frame], coords: CoordinateSystem, fps: f64) -> Result<String> {
    check(frames, fps)?;
    // BVH wants the native local R below the root and S_g R at the root (the rest pose
    // stays in the skeleton's frame, y up).
    let t = ToFile::new(coords);
    let mut out = String::from("HIERARCHY\n");
    hierarchy(&mut out, rest, 0, 0);
    motion_header(&mut out, frames.len(), fps);
    // Channel order is the hierarchy's depth-first order.
    let mut order = Vec::with_capacity(CG_NUM_JOINTS);
    fn visit(j: usize, order: &mut Vec<usize>) {
        order.push(j);
        for c in children(j) {
            visit(c, order);
        }
    }
    visit(0, &mut order);
    for f in frames {
        let q = local_rotations(f);
        let p = t.point(&f.root_translation);
        let mut line = format!("{:.6} {:.6} {:.6}", p[0], p[1], p[2]);
        for &j in &order {
            let r = t.native(&q[j]);
            let r = if j == 0 { mat_mul(&t.g, &r) } else { r };
            push_rotation(&mut line, &r);
        }
        out.push_str(&line);
        out.push('\n');
    }
    Ok(out)
}

/// The object's track: a one-joint hierarchy, its origin and rotation per frame (`frames`
/// in `coords`).
pub fn object(frames: &[Frame], coords: CoordinateSystem, fps: f64) -> Result<String> {
    check(frames, fps)?;
    let t = ToFile::new(coords);
    let mut out = String::from(
        "HIERARCHY\nROOT object\n{\n  OFFSET 0.000000 0.000000 0.000000\n  \
         CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n  \
         End Site\n  {\n    OFFSET 0.000000 5.000000 0.000000\n  }\n}\n",
    );
    motion_header(&mut out, frames.len(), fps);
    for f in frames {
        let p = t.point(&f.object_translation);
        let mut line = format!("{:.6} {:.6} {:.6}", p[0], p[1], p[2]);
        push_rotation(&mut line, &mat_mul(&mat_mul(&t.g, &t.native(&f.object_rotation)), &t.gt));
        out.push_str(&line);
        out.push('\n');
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::skeleton::axis_angle;

    #[test]
    fn euler_angles_rebuild_the_rotation() {
        let rz = |a: f64| axis_angle(&[0.0, 0.0, 1.0], a.to_radians());
        let rx = |a: f64| axis_angle(&[1.0, 0.0, 0.0], a.to_radians());
        let ry = |a: f64| axis_angle(&[0.0, 1.0, 0.0], a.to_radians());
        for (z, x, y) in [(10.0, 20.0, 30.0), (-170.0, 80.0, 5.0), (0.0, -45.0, 179.0), (33.0, 90.0, 0.0)] {
            let r = mat_mul(&mat_mul(&rz(z), &rx(x)), &ry(y));
            let [ez, ex, ey] = zxy_degrees(&r);
            let back = mat_mul(&mat_mul(&rz(ez), &rx(ex)), &ry(ey));
            for i in 0..3 {
                for k in 0..3 {
                    assert!((back[i][k] - r[i][k]).abs() < 1e-9, "{z} {x} {y}");
                }
            }
        }
    }
}
