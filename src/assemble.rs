//! Frame assembly: one normalized 335-D decoder frame → one C [`Frame`] in the engine's
//! coordinate system (DESIGN §2, §5).
//!
//! Steps: de-normalize (`x * std + mean` in `f32`, exactly as the Python exporter, so the
//! parity file `case0_frames_denormalized.npy` is reproduced bit for bit; the two contact
//! channels are already probabilities and are only clamped to [0, 1]), 6D → rotation
//! matrix (Gram–Schmidt, [`rot6d_to_matrix`]), basis change, matrix → unit quaternion
//! `(x, y, z, w)` with `w >= 0`, translations / object centre / wrist vectors, contact
//! probability and flag (`> 0.5`), `time_s = frame_index / fps`, and optionally forward
//! kinematics on the bundle skeleton. [`FrameAssembler::assemble`] never allocates.
//!
//! # Coordinate systems
//!
//! The native world is GRAB's: z up, right-handed, metres. Another system is the SAME
//! data seen in another basis: a fixed signed permutation `S` (orthogonal, `det ±1`) and
//! a unit scale `c`:
//!
//! | system | `(x', y', z')` from native `(x, y, z)` | `det S` | units |
//! | --- | --- | --- | --- |
//! | native | `(x, y, z)` | +1 | m |
//! | glTF (y up, right-handed) | `(x, z, −y)` (Blender's glTF exporter convention) | +1 | m |
//! | Unity (y up, left-handed) | `(−x, z, −y)` = glTF with x mirrored, as glTFast and UnityGLTF import glTF | −1 | m |
//! | Unreal (z up, left-handed) | `(x, −y, z) · 100` (y mirrored, as FBX→Unreal) | −1 | cm |
//!
//! * Positions and vectors (root / object translation, object centre, wrist-to-object,
//!   joint positions): `p' = c · S p`.
//! * EVERY rotation, global (root, object) and local (body, fingers) alike:
//!   `R' = S R Sᵀ` (a proper rotation even when `S` is a mirror, since `det S² = 1`), then
//!   the quaternion of `R'` (the standard matrix↔quaternion algebra, which Unity's
//!   `Quaternion` and Unreal's `FQuat` also use).
//! * Consequently a host must express its REST skeleton in the same basis:
//!   `J'_i = c · S J_i` with `J` the bundle's rest joints (manifest, SMPL-X canonical rest
//!   frame), and object meshes as `v' = c · S v`. Then the host's own FK
//!   `G'_i = G'_parent R'_i`, `p'_i = p'_parent + G'_parent (J'_i − J'_parent)`,
//!   `p'_0 = root_translation` reproduces `joint_positions` exactly (tested), because
//!   `S Sᵀ = I`. [`FrameAssembler::rest_joints`] returns `J'`.

use crate::error::{Error, Result};
use crate::frame::{cg_coordinate_system, CoordinateSystem, Frame, CG_BODY_JOINTS, CG_HAND_JOINTS, CG_NUM_JOINTS};
use crate::skeleton::{
    mat_mul, mat_vec, matrix_to_quaternion, quaternion_to_matrix, rot6d_to_matrix, transpose, Mat3, Skeleton, Vec3,
    IDENTITY,
};

/// Width of one frame's feature vector.
pub const FRAME_DIM: usize = 335;
/// Feature channels that are contact probabilities (left, right): not de-normalized.
pub const CONTACT_CHANNELS: [usize; 2] = [240, 334];
/// Contact flag threshold on the probability.
pub const CONTACT_THRESHOLD: f32 = 0.5;

const ROOT_ROT6D: usize = 0;
const ROOT_TRANSL: usize = 6;
const OBJECT_ROT6D: usize = 9;
const OBJECT_TRANSL: usize = 15;
const OBJECT_CENTRE: usize = 18;
const BODY_ROT6D: usize = 21; // joints 1..21
const LHAND_ROT6D: usize = 147; // joints 25..39
const LWRIST_TO_OBJECT: usize = 237;
const RHAND_ROT6D: usize = 241; // joints 40..54
const RWRIST_TO_OBJECT: usize = 331;
/// First SMPL-X joint of each hand's 15 finger joints.
const LHAND_FIRST_JOINT: usize = 25;
const RHAND_FIRST_JOINT: usize = 40;

/// Column of joint `j`'s 6D in the 335-D vector, `None` for jaw and eyes (identity).
pub const fn rot6d_column(j: usize) -> Option<usize> {
    match j {
        0 => Some(ROOT_ROT6D),
        1..=21 => Some(BODY_ROT6D + 6 * (j - 1)),
        25..=39 => Some(LHAND_ROT6D + 6 * (j - LHAND_FIRST_JOINT)),
        40..=54 => Some(RHAND_ROT6D + 6 * (j - RHAND_FIRST_JOINT)),
        _ => None,
    }
}

impl cg_coordinate_system {
    /// The basis change `S` (row-major, `p' = scale · S p`) and unit scale from the
    /// native world (z up, right-handed, metres). See the module docs for the table.
    pub fn basis(self) -> (Mat3, f64) {
        match self {
            cg_coordinate_system::CG_COORDS_NATIVE => (IDENTITY, 1.0),
            // (x, y, z) -> (x, z, -y)
            cg_coordinate_system::CG_COORDS_GLTF => ([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], 1.0),
            // (x, y, z) -> (-x, z, -y)
            cg_coordinate_system::CG_COORDS_UNITY => ([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], 1.0),
            // (x, y, z) -> 100 (x, -y, z)
            cg_coordinate_system::CG_COORDS_UNREAL => ([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]], 100.0),
        }
    }

    /// A native point or vector in this system: `c · S p` (what frames get).
    pub fn from_native_point(self, p: &Vec3) -> Vec3 {
        let (s, c) = self.basis();
        mat_vec(&s, p).map(|v| v * c)
    }

    /// A point or vector of this system in the native world: `S^T p / c` (the inverse of
    /// what frames get).
    pub fn to_native_point(self, p: &Vec3) -> Vec3 {
        let (s, c) = self.basis();
        mat_vec(&transpose(&s), p).map(|v| v / c)
    }

    /// A rotation of this system in the native world: `S^T R S`.
    pub fn to_native_rotation(self, r: &Mat3) -> Mat3 {
        let (s, _) = self.basis();
        mat_mul(&mat_mul(&transpose(&s), r), &s)
    }
}

/// The basis change of one coordinate system, applied to points and rotations.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Basis {
    s: Mat3,
    st: Mat3,
    scale: f64,
}

impl Basis {
    fn new(coords: CoordinateSystem) -> Self {
        let (s, scale) = coords.basis();
        Basis { s, st: transpose(&s), scale }
    }

    fn point(&self, p: &Vec3) -> [f32; 3] {
        let q = mat_vec(&self.s, p);
        [(q[0] * self.scale) as f32, (q[1] * self.scale) as f32, (q[2] * self.scale) as f32]
    }

    fn rotation(&self, r: &Mat3) -> [f32; 4] {
        let q = matrix_to_quaternion(&mat_mul(&mat_mul(&self.s, r), &self.st));
        q.map(|v| v as f32)
    }
}

/// Turns normalized decoder frames into C frames. Built once per engine (it holds the
/// normalization statistics, the skeleton and the coordinate system); `assemble` takes
/// `&self`, so one assembler serves every stream and thread.
#[derive(Clone, Debug)]
pub struct FrameAssembler {
    mean: [f32; FRAME_DIM],
    std: [f32; FRAME_DIM],
    skeleton: Skeleton,
    coords: CoordinateSystem,
    basis: Basis,
    with_fk: bool,
    fps: f64,
}

fn vec3(f: &[f32; FRAME_DIM], at: usize) -> Vec3 {
    [f[at] as f64, f[at + 1] as f64, f[at + 2] as f64]
}

fn rot6d(f: &[f32; FRAME_DIM], at: usize) -> Mat3 {
    let d: [f64; 6] = std::array::from_fn(|i| f[at + i] as f64);
    rot6d_to_matrix(&d)
}

/// A contact probability as a host may rely on it: in [0, 1], NaN → 0.
fn clamp_probability(p: f32) -> f32 {
    if p >= 1.0 {
        1.0
    } else if p > 0.0 {
        p
    } else {
        0.0
    }
}

impl FrameAssembler {
    /// `mean` / `std`: the manifest's normalization (335 each, finite); `parents` /
    /// `rest_joints`: the manifest's skeleton (55 joints, see [`Skeleton::new`]);
    /// `with_fk`: fill `joint_positions`; `fps`: the bundle's frame rate (> 0).
    /// Errors are [`Error::InvalidArgument`].
    pub fn new(
        mean: &[f32],
        std: &[f32],
        parents: &[i32],
        rest_joints: &[[f32; 3]],
        coords: CoordinateSystem,
        with_fk: bool,
        fps: f64,
    ) -> Result<Self> {
        if mean.len() != FRAME_DIM || std.len() != FRAME_DIM {
            return Err(Error::InvalidArgument(format!(
                "normalization: expected {FRAME_DIM} mean and std values, got {} and {}",
                mean.len(),
                std.len()
            )));
        }
        if let Some(i) = mean.iter().chain(std.iter()).position(|v| !v.is_finite()) {
            return Err(Error::InvalidArgument(format!(
                "normalization: non-finite {} at channel {}",
                if i < FRAME_DIM { "mean" } else { "std" },
                i % FRAME_DIM
            )));
        }
        if !(fps.is_finite() && fps > 0.0) {
            return Err(Error::InvalidArgument(format!("fps must be finite and > 0, got {fps}")));
        }
        let skeleton = Skeleton::new(parents, rest_joints)?;
        let mut a = FrameAssembler {
            mean: [0.0; FRAME_DIM],
            std: [0.0; FRAME_DIM],
            skeleton,
            coords,
            basis: Basis::new(coords),
            with_fk,
            fps,
        };
        a.mean.copy_from_slice(mean);
        a.std.copy_from_slice(std);
        Ok(a)
    }

    pub fn coordinate_system(&self) -> CoordinateSystem {
        self.coords
    }

    pub fn with_fk(&self) -> bool {
        self.with_fk
    }

    pub fn fps(&self) -> f64 {
        self.fps
    }

    pub fn skeleton(&self) -> &Skeleton {
        &self.skeleton
    }

    /// The rest skeleton in the output coordinate system and units (`c · S J`): what a
    /// host's rest pose must be for the frame's local rotations to mean the same motion
    /// (see the module docs).
    pub fn rest_joints(&self) -> [[f32; 3]; CG_NUM_JOINTS] {
        std::array::from_fn(|j| self.basis.point(&self.skeleton.rest_joints()[j]))
    }

    /// De-normalizes one frame: `x * std + mean` in `f32` (two roundings, as numpy),
    /// contact channels clamped to [0, 1] instead.
    pub fn denormalize(&self, normalized: &[f32], out: &mut [f32; FRAME_DIM]) {
        assert_eq!(normalized.len(), FRAME_DIM, "a frame has {FRAME_DIM} features");
        for i in 0..FRAME_DIM {
            out[i] = normalized[i] * self.std[i] + self.mean[i];
        }
        for c in CONTACT_CHANNELS {
            out[c] = clamp_probability(normalized[c]);
        }
    }

    /// Fills `out` from one normalized frame (335 features, as the decoder emits them): the
    /// model's raw output, [`Self::decode`] then [`Self::emit`]. Every field of `out` is
    /// written. No allocation.
    ///
    /// Panics if `normalized.len() != 335` (a caller bug: the decoder's frame width is
    /// checked when the bundle is loaded).
    pub fn assemble(&self, normalized: &[f32], stream_id: u64, frame_index: u64, is_last: bool, out: &mut Frame) {
        let mut pose = Pose::default();
        self.decode(normalized, &mut pose);
        self.emit(&pose, stream_id, frame_index, is_last, out);
    }

    /// One normalized frame → its [`Pose`] in the native world (de-normalized, 6D turned
    /// into rotation matrices). No allocation.
    pub fn decode(&self, normalized: &[f32], pose: &mut Pose) {
        let mut f = [0.0f32; FRAME_DIM];
        self.denormalize(normalized, &mut f);
        for (j, l) in pose.local.iter_mut().enumerate() {
            *l = match rot6d_column(j) {
                Some(col) => rot6d(&f, col),
                None => IDENTITY,
            };
        }
        pose.pelvis = vec3(&f, ROOT_TRANSL);
        pose.object_rotation = rot6d(&f, OBJECT_ROT6D);
        pose.object_translation = vec3(&f, OBJECT_TRANSL);
        pose.object_centre = vec3(&f, OBJECT_CENTRE);
        pose.wrist_to_object = [vec3(&f, LWRIST_TO_OBJECT), vec3(&f, RWRIST_TO_OBJECT)];
        pose.contact_probability = [f[CONTACT_CHANNELS[0]], f[CONTACT_CHANNELS[1]]];
        pose.contact = pose.contact_probability.map(|v| v > CONTACT_THRESHOLD);
    }

    /// A native-world [`Pose`] → the C frame in the engine's coordinate system (basis change,
    /// quaternions, FK when enabled). Every field of `out` is written. No allocation.
    pub fn emit(&self, pose: &Pose, stream_id: u64, frame_index: u64, is_last: bool, out: &mut Frame) {
        let b = &self.basis;
        let local = &pose.local;
        out.stream_id = stream_id;
        out.frame_index = frame_index;
        out.time_s = frame_index as f64 / self.fps;
        out.root_translation = b.point(&pose.pelvis);
        out.root_rotation = b.rotation(&local[0]);
        for i in 0..CG_BODY_JOINTS {
            out.body_rotations[i] = b.rotation(&local[1 + i]);
        }
        for i in 0..CG_HAND_JOINTS {
            out.left_hand_rotations[i] = b.rotation(&local[LHAND_FIRST_JOINT + i]);
            out.right_hand_rotations[i] = b.rotation(&local[RHAND_FIRST_JOINT + i]);
        }
        out.object_translation = b.point(&pose.object_translation);
        out.object_rotation = b.rotation(&pose.object_rotation);
        out.object_centre = b.point(&pose.object_centre);
        out.left_wrist_to_object = b.point(&pose.wrist_to_object[0]);
        out.right_wrist_to_object = b.point(&pose.wrist_to_object[1]);
        out.contact_probability = pose.contact_probability;
        out.contact = pose.contact.map(u8::from);
        out.is_last = u8::from(is_last);
        out.reserved = [0; 4];
        if self.with_fk {
            let mut global = [IDENTITY; CG_NUM_JOINTS];
            let mut pos = [[0.0f64; 3]; CG_NUM_JOINTS];
            self.skeleton.forward(local, pose.pelvis, &mut global, &mut pos);
            for (o, p) in out.joint_positions.iter_mut().zip(pos.iter()) {
                *o = b.point(p);
            }
            out.has_joint_positions = 1;
        } else {
            out.joint_positions = [[0.0; 3]; CG_NUM_JOINTS];
            out.has_joint_positions = 0;
        }
    }
}

/// One frame in the native world (z up, metres), between decoding and the basis change:
/// what the contact stage (`crate::contact`) reads and corrects.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    /// Local rotations of the 55 joints (0 = the root's global rotation; jaw and eyes identity).
    pub local: [Mat3; CG_NUM_JOINTS],
    /// World position of the pelvis.
    pub pelvis: Vec3,
    pub object_rotation: Mat3,
    pub object_translation: Vec3,
    /// World position of the object's bounding-box centre.
    pub object_centre: Vec3,
    /// Wrist position minus the object centre, [left, right].
    pub wrist_to_object: [Vec3; 2],
    /// Contact probability per hand, in [0, 1].
    pub contact_probability: [f32; 2],
    /// Contact flag per hand.
    pub contact: [bool; 2],
}

impl Pose {
    /// Moves the whole frame by the rigid motion `p -> r p + t` (native world): root,
    /// object and the wrist-to-object vectors; local rotations below the root are unchanged.
    pub fn transform(&mut self, r: &Mat3, t: &Vec3) {
        let moved = |p: &Vec3| {
            let q = mat_vec(r, p);
            [q[0] + t[0], q[1] + t[1], q[2] + t[2]]
        };
        self.local[0] = mat_mul(r, &self.local[0]);
        self.pelvis = moved(&self.pelvis);
        self.object_rotation = mat_mul(r, &self.object_rotation);
        self.object_translation = moved(&self.object_translation);
        self.object_centre = moved(&self.object_centre);
        self.wrist_to_object = self.wrist_to_object.map(|v| mat_vec(r, &v));
    }
}

impl Pose {
    /// Blends the body from `from` (weight `1 - s`) to this pose (weight `s`): every local
    /// rotation by normalized quaternion interpolation, the pelvis linearly. The object and
    /// contact fields are this pose's (the contact stage owns them).
    pub fn blend_from(&mut self, from: &Pose, s: f64) {
        for (l, f) in self.local.iter_mut().zip(&from.local) {
            let (a, b) = (matrix_to_quaternion(f), matrix_to_quaternion(l));
            let sign = if (0..4).map(|i| a[i] * b[i]).sum::<f64>() < 0.0 { -1.0 } else { 1.0 };
            let q: [f64; 4] = std::array::from_fn(|i| (1.0 - s) * a[i] + s * sign * b[i]);
            let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            if n > 1e-12 {
                *l = quaternion_to_matrix(&q.map(|v| v / n));
            }
        }
        for i in 0..3 {
            self.pelvis[i] = (1.0 - s) * from.pelvis[i] + s * self.pelvis[i];
        }
    }
}

impl Default for Pose {
    fn default() -> Self {
        Pose {
            local: [IDENTITY; CG_NUM_JOINTS],
            pelvis: [0.0; 3],
            object_rotation: IDENTITY,
            object_translation: [0.0; 3],
            object_centre: [0.0; 3],
            wrist_to_object: [[0.0; 3]; 2],
            contact_probability: [0.0; 2],
            contact: [false; 2],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampler::SplitMix64;
    use crate::skeleton::tests::random_rotation;
    use crate::skeleton::{det, quaternion_to_matrix, SMPLX_PARENTS};

    const ALL: [CoordinateSystem; 4] = [
        cg_coordinate_system::CG_COORDS_NATIVE,
        cg_coordinate_system::CG_COORDS_GLTF,
        cg_coordinate_system::CG_COORDS_UNITY,
        cg_coordinate_system::CG_COORDS_UNREAL,
    ];

    /// A plausible rest skeleton (not the bundle's numbers; any tree works).
    fn rest() -> Vec<[f32; 3]> {
        (0..55)
            .map(|j| {
                let t = j as f32;
                [0.03 * (t * 1.3).sin(), -0.35 + 0.02 * (t * 0.7).cos() + 0.01 * t, 0.01 * (t * 2.1).sin()]
            })
            .collect()
    }

    /// A random de-normalized frame with noisy (non-orthonormal) 6D, and mean/std that
    /// make `normalized` give it back.
    fn random_frame(r: &mut SplitMix64) -> (Vec<f32>, [f32; FRAME_DIM], [f32; FRAME_DIM]) {
        let mut x = vec![0.0f32; FRAME_DIM];
        for v in x.iter_mut() {
            *v = (r.next_uniform() * 2.0 - 1.0) as f32;
        }
        for j in (0..55).filter_map(rot6d_column).chain([OBJECT_ROT6D]) {
            let m = random_rotation(r);
            for i in 0..6 {
                x[j + i] = (m[i / 3][i % 3] + 0.05 * (r.next_uniform() - 0.5)) as f32;
            }
        }
        x[CONTACT_CHANNELS[0]] = 0.2;
        x[CONTACT_CHANNELS[1]] = 0.9;
        let mean: [f32; FRAME_DIM] = std::array::from_fn(|i| if CONTACT_CHANNELS.contains(&i) { 0.0 } else { 0.25 });
        let std: [f32; FRAME_DIM] = std::array::from_fn(|i| if CONTACT_CHANNELS.contains(&i) { 1.0 } else { 0.5 });
        // normalized such that normalized * std + mean is x (up to f32 rounding).
        let norm = x.iter().enumerate().map(|(i, &v)| (v - mean[i]) / std[i]).collect();
        (norm, mean, std)
    }

    fn quat_mat(q: &[f32; 4]) -> Mat3 {
        quaternion_to_matrix(&q.map(f64::from))
    }

    fn close3(a: &[f32; 3], b: &[f32; 3], tol: f32) -> bool {
        (0..3).all(|i| (a[i] - b[i]).abs() <= tol)
    }

    #[test]
    fn bases_are_what_the_docs_say() {
        let (p, q) = ([1.0, 2.0, 3.0], ALL.map(|c| Basis::new(c).point(&[1.0, 2.0, 3.0])));
        let _ = p;
        assert_eq!(q, [[1.0, 2.0, 3.0], [1.0, 3.0, -2.0], [-1.0, 3.0, -2.0], [100.0, -200.0, 300.0]]);
        let dets = ALL.map(|c| det(&c.basis().0));
        assert_eq!(dets, [1.0, 1.0, -1.0, -1.0]); // right-, right-, left-, left-handed
                                                  // Up axis: native +z becomes +y in glTF/Unity, stays +z (cm) in Unreal.
        let up = ALL.map(|c| Basis::new(c).point(&[0.0, 0.0, 1.0]));
        assert_eq!(up, [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 100.0]]);
    }

    #[test]
    fn every_coordinate_system_is_consistent() {
        let mut r = SplitMix64::new(5);
        let rest = rest();
        let (norm, mean, std) = random_frame(&mut r);
        let native =
            FrameAssembler::new(&mean, &std, &SMPLX_PARENTS, &rest, cg_coordinate_system::CG_COORDS_NATIVE, true, 30.0)
                .unwrap();
        let mut f0 = Frame::default();
        native.assemble(&norm, 9, 45, true, &mut f0);
        assert_eq!((f0.stream_id, f0.frame_index, f0.time_s, f0.is_last), (9, 45, 1.5, 1));
        assert_eq!((f0.contact_probability, f0.contact), ([0.2, 0.9], [0, 1]));
        // Native FK pelvis is the root translation.
        assert_eq!(f0.joint_positions[0], f0.root_translation);

        for coords in ALL {
            let a = FrameAssembler::new(&mean, &std, &SMPLX_PARENTS, &rest, coords, true, 30.0).unwrap();
            let mut f = Frame::default();
            a.assemble(&norm, 9, 45, false, &mut f);
            let b = Basis::new(coords);
            let tol = 1e-5 * b.scale as f32;
            let pt = |p: &[f32; 3]| b.point(&p.map(f64::from));
            // Positions and vectors transformed.
            assert!(close3(&f.root_translation, &pt(&f0.root_translation), tol));
            assert!(close3(&f.object_translation, &pt(&f0.object_translation), tol));
            assert!(close3(&f.object_centre, &pt(&f0.object_centre), tol));
            assert!(close3(&f.left_wrist_to_object, &pt(&f0.left_wrist_to_object), tol));
            assert!(close3(&f.right_wrist_to_object, &pt(&f0.right_wrist_to_object), tol));
            // FK positions = transformed native FK positions.
            for j in 0..55 {
                assert!(close3(&f.joint_positions[j], &pt(&f0.joint_positions[j]), tol), "{coords:?} joint {j}");
            }
            // Unit quaternions, w >= 0, proper rotations equal to S R S^T.
            let rots = |fr: &Frame| -> Vec<[f32; 4]> {
                let mut v = vec![fr.root_rotation, fr.object_rotation];
                v.extend_from_slice(&fr.body_rotations);
                v.extend_from_slice(&fr.left_hand_rotations);
                v.extend_from_slice(&fr.right_hand_rotations);
                v
            };
            for (q, q0) in rots(&f).iter().zip(rots(&f0).iter()) {
                let n: f32 = q.iter().map(|v| v * v).sum();
                assert!((n - 1.0).abs() < 1e-6 && q[3] >= 0.0);
                let m = quat_mat(q);
                assert!((det(&m) - 1.0).abs() < 1e-5);
                let want = mat_mul(&mat_mul(&b.s, &quat_mat(q0)), &b.st);
                for i in 0..3 {
                    for k in 0..3 {
                        assert!((m[i][k] - want[i][k]).abs() < 1e-5);
                    }
                }
            }
            // A host's FK in the output basis (quaternions + transformed rest joints)
            // reproduces joint_positions.
            let rest_out = a.rest_joints();
            let mut local = [IDENTITY; 55];
            local[0] = quat_mat(&f.root_rotation);
            for i in 0..21 {
                local[1 + i] = quat_mat(&f.body_rotations[i]);
            }
            for i in 0..15 {
                local[25 + i] = quat_mat(&f.left_hand_rotations[i]);
                local[40 + i] = quat_mat(&f.right_hand_rotations[i]);
            }
            let host = Skeleton::new(&SMPLX_PARENTS, &rest_out).unwrap();
            let (mut g, mut pos) = ([IDENTITY; 55], [[0.0; 3]; 55]);
            host.forward(&local, f.root_translation.map(f64::from), &mut g, &mut pos);
            for (j, p) in pos.iter().enumerate() {
                let p = p.map(|v| v as f32);
                assert!(close3(&p, &f.joint_positions[j], 2e-5 * b.scale as f32), "{coords:?} host FK joint {j}");
            }
        }
    }

    #[test]
    fn unreal_is_in_centimetres() {
        let mut r = SplitMix64::new(8);
        let rest = rest();
        let (norm, mean, std) = random_frame(&mut r);
        let mk = |c| FrameAssembler::new(&mean, &std, &SMPLX_PARENTS, &rest, c, true, 30.0).unwrap();
        let (mut a, mut b) = (Frame::default(), Frame::default());
        mk(cg_coordinate_system::CG_COORDS_NATIVE).assemble(&norm, 0, 0, false, &mut a);
        mk(cg_coordinate_system::CG_COORDS_UNREAL).assemble(&norm, 0, 0, false, &mut b);
        let want = [a.root_translation[0] * 100.0, -a.root_translation[1] * 100.0, a.root_translation[2] * 100.0];
        assert!(close3(&b.root_translation, &want, 1e-4));
        let (la, lb) = (
            (0..3).map(|i| (a.joint_positions[20][i] - a.joint_positions[18][i]).powi(2)).sum::<f32>().sqrt(),
            (0..3).map(|i| (b.joint_positions[20][i] - b.joint_positions[18][i]).powi(2)).sum::<f32>().sqrt(),
        );
        assert!((lb / la - 100.0).abs() < 1e-3); // forearm length in cm
    }

    #[test]
    fn without_fk_and_contacts_clamped() {
        let mut r = SplitMix64::new(2);
        let rest = rest();
        let (mut norm, mean, std) = random_frame(&mut r);
        norm[CONTACT_CHANNELS[0]] = 1.7;
        norm[CONTACT_CHANNELS[1]] = f32::NAN;
        let a =
            FrameAssembler::new(&mean, &std, &SMPLX_PARENTS, &rest, cg_coordinate_system::CG_COORDS_GLTF, false, 30.0)
                .unwrap();
        let mut f = Frame::default();
        f.joint_positions[3] = [1.0; 3];
        a.assemble(&norm, 1, 2, false, &mut f);
        assert_eq!(f.has_joint_positions, 0);
        assert!(f.joint_positions.iter().all(|p| *p == [0.0; 3]));
        assert_eq!((f.contact_probability, f.contact), ([1.0, 0.0], [1, 0]));
        let mut n2 = norm.clone();
        n2[CONTACT_CHANNELS[0]] = -0.3;
        n2[CONTACT_CHANNELS[1]] = 0.5; // not > 0.5
        a.assemble(&n2, 1, 2, false, &mut f);
        assert_eq!((f.contact_probability, f.contact), ([0.0, 0.5], [0, 0]));
    }

    #[test]
    fn constructor_validation() {
        let rest = rest();
        let m = [0.0f32; FRAME_DIM];
        let s = [1.0f32; FRAME_DIM];
        let n = cg_coordinate_system::CG_COORDS_NATIVE;
        assert!(FrameAssembler::new(&m, &s, &SMPLX_PARENTS, &rest, n, true, 30.0).is_ok());
        assert!(FrameAssembler::new(&m[..334], &s, &SMPLX_PARENTS, &rest, n, true, 30.0).is_err());
        assert!(FrameAssembler::new(&m, &s, &SMPLX_PARENTS, &rest, n, true, 0.0).is_err());
        assert!(FrameAssembler::new(&m, &s, &SMPLX_PARENTS, &rest, n, true, f64::NAN).is_err());
        assert!(FrameAssembler::new(&m, &s, &SMPLX_PARENTS[..10], &rest, n, true, 30.0).is_err());
        let mut bad = s;
        bad[7] = f32::INFINITY;
        assert!(matches!(
            FrameAssembler::new(&m, &bad, &SMPLX_PARENTS, &rest, n, true, 30.0),
            Err(Error::InvalidArgument(_))
        ));
    }

    #[test]
    fn jaw_and_eyes_are_identity_and_columns_tile_the_layout() {
        let cols: Vec<usize> = (0..55).filter_map(rot6d_column).collect();
        assert_eq!(cols.len(), 52);
        assert_eq!([rot6d_column(22), rot6d_column(23), rot6d_column(24)], [None, None, None]);
        assert_eq!(
            (rot6d_column(21), rot6d_column(25), rot6d_column(39), rot6d_column(40), rot6d_column(54)),
            (Some(141), Some(147), Some(231), Some(241), Some(325))
        );
        // With FK on the identity pose of jaw/eyes, their world position follows the head.
        let mut r = SplitMix64::new(3);
        let rest = rest();
        let (norm, mean, std) = random_frame(&mut r);
        let a =
            FrameAssembler::new(&mean, &std, &SMPLX_PARENTS, &rest, cg_coordinate_system::CG_COORDS_NATIVE, true, 30.0)
                .unwrap();
        let mut f = Frame::default();
        a.assemble(&norm, 0, 0, false, &mut f);
        // Distance jaw-head equals the rest distance (rigid child of the head).
        let d = |p: [f32; 3], q: [f32; 3]| (0..3).map(|i| (p[i] - q[i]).powi(2)).sum::<f32>().sqrt();
        assert!((d(f.joint_positions[22], f.joint_positions[15]) - d(rest[22], rest[15])).abs() < 1e-5);
    }
}
