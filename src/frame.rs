//! The frame a host receives, `#[repr(C)]` with a fixed layout (it is also the iceoryx2
//! payload), and the coordinate systems a host can ask for.
//!
//! Rotations are unit quaternions stored (x, y, z, w) with w >= 0, the order glTF, Unity and
//! Unreal use. Body/finger rotations are LOCAL (relative to the parent joint of the SMPL-X
//! tree, in the bundle skeleton's rest frame); root and object rotations are global.
//!
//! A coordinate system other than native is the same data in another basis: with the
//! basis change `S` and unit scale `c` of [`cg_coordinate_system`], positions and vectors
//! become `c * S * p` and EVERY rotation (global and local) becomes `S * R * S^T`. A host's
//! rest skeleton (and object meshes) must use the same change, `c * S * J`, for its own
//! forward kinematics to reproduce `joint_positions` (`assemble::FrameAssembler` docs).

/// Body joints 1..21 of the SMPL-X tree.
pub const CG_BODY_JOINTS: usize = 21;
/// Finger joints per hand (SMPL-X 25..39 left, 40..54 right).
pub const CG_HAND_JOINTS: usize = 15;
/// All joints of the SMPL-X tree (jaw and eyes included, always identity).
pub const CG_NUM_JOINTS: usize = 55;

/// One frame of generated motion. All positions in the engine's coordinate system
/// (metres, or centimetres for Unreal). Rotations are unit quaternions (x, y, z, w) with
/// w >= 0. In a non-native coordinate system with basis change S and unit scale c (see
/// cg_coordinate_system), positions are c * S * p and EVERY rotation, global and local
/// alike, is S * R * S^T: a host's rest skeleton (and object meshes) must be transformed
/// the same way (c * S * J) for its forward kinematics to match `joint_positions`.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct cg_frame {
    /// Id of the stream that produced the frame (unique per engine).
    pub stream_id: u64,
    /// 0-based index of the frame in its stream.
    pub frame_index: u64,
    /// frame_index / fps, seconds.
    pub time_s: f64,
    /// World position of the pelvis (root joint).
    pub root_translation: [f32; 3],
    /// Global rotation of the pelvis, quaternion (x, y, z, w).
    pub root_rotation: [f32; 4],
    /// Local rotations of SMPL-X joints 1..21, quaternions (x, y, z, w).
    pub body_rotations: [[f32; 4]; CG_BODY_JOINTS],
    /// Local rotations of the left-hand finger joints (SMPL-X 25..39).
    pub left_hand_rotations: [[f32; 4]; CG_HAND_JOINTS],
    /// Local rotations of the right-hand finger joints (SMPL-X 40..54).
    pub right_hand_rotations: [[f32; 4]; CG_HAND_JOINTS],
    /// World position of the object's origin.
    pub object_translation: [f32; 3],
    /// Global rotation of the object, quaternion (x, y, z, w).
    pub object_rotation: [f32; 4],
    /// World position of the object's bounding-box centre.
    pub object_centre: [f32; 3],
    /// Left wrist position minus the object centre.
    pub left_wrist_to_object: [f32; 3],
    /// Right wrist position minus the object centre.
    pub right_wrist_to_object: [f32; 3],
    /// Contact probability per hand [left, right], 0..1.
    pub contact_probability: [f32; 2],
    /// Per hand [left, right]: 1 while the hand holds the object (the contact-consistency
    /// stage's debounced decision; with CG_STREAM_RAW_OUTPUT, probability > 0.5), else 0.
    pub contact: [u8; 2],
    /// 1 on the last frame of the stream, else 0.
    pub is_last: u8,
    /// 1 when `joint_positions` is filled (forward kinematics enabled), else 0.
    pub has_joint_positions: u8,
    /// Padding, always 0.
    pub reserved: [u8; 4],
    /// World positions of the 55 joints (only when has_joint_positions is 1).
    pub joint_positions: [[f32; 3]; CG_NUM_JOINTS],
}

pub type Frame = cg_frame;

impl Default for cg_frame {
    fn default() -> Self {
        // SAFETY-free zero frame: every field is plain data for which all-zero is valid.
        cg_frame {
            stream_id: 0,
            frame_index: 0,
            time_s: 0.0,
            root_translation: [0.0; 3],
            root_rotation: [0.0, 0.0, 0.0, 1.0],
            body_rotations: [[0.0, 0.0, 0.0, 1.0]; CG_BODY_JOINTS],
            left_hand_rotations: [[0.0, 0.0, 0.0, 1.0]; CG_HAND_JOINTS],
            right_hand_rotations: [[0.0, 0.0, 0.0, 1.0]; CG_HAND_JOINTS],
            object_translation: [0.0; 3],
            object_rotation: [0.0, 0.0, 0.0, 1.0],
            object_centre: [0.0; 3],
            left_wrist_to_object: [0.0; 3],
            right_wrist_to_object: [0.0; 3],
            contact_probability: [0.0; 2],
            contact: [0; 2],
            is_last: 0,
            has_joint_positions: 0,
            reserved: [0; 4],
            joint_positions: [[0.0; 3]; CG_NUM_JOINTS],
        }
    }
}

/// The coordinate system frames are expressed in, chosen at engine creation.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum cg_coordinate_system {
    /// The bundle's own: z up, right-handed, metres (GRAB's world). `S` = identity.
    #[default]
    CG_COORDS_NATIVE = 0,
    /// glTF: y up, right-handed, metres. (x, y, z) -> (x, z, -y) (a rotation, det +1).
    CG_COORDS_GLTF = 1,
    /// Unity: y up, left-handed, metres. (x, y, z) -> (-x, z, -y) (a mirror, det -1:
    /// the glTF mapping with x negated, as glTFast / UnityGLTF import glTF).
    CG_COORDS_UNITY = 2,
    /// Unreal: z up, left-handed, centimetres. (x, y, z) -> 100 * (x, -y, z) (a mirror).
    CG_COORDS_UNREAL = 3,
}

pub type CoordinateSystem = cg_coordinate_system;
