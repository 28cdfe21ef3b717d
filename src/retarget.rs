//! Retargeting: the engine's frames on a host's own skeleton (docs/retargeting.md).
//!
//! A game character is not SMPL-X: other bone names, another rest pose (T or A), other
//! proportions and local axes. The host describes its skeleton once ([`HostSkeleton`]: bone
//! names, parents, rest local transforms, in the engine's coordinate system and units) and a
//! map from SMPL-X joints to its bones ([`builtin_map`] for the Unity Humanoid bone set, the
//! UE5 Mannequin and Mixamo, or its own); a [`Retargeter`] then fills one pose per bone for
//! every frame, allocation-free.
//!
//! The transfer is rest-pose relative and in world space, so rest poses and axis
//! conventions need not match. SMPL-X's rest globals are the identity, so a frame's global
//! joint rotation `G_j` is also its rotation from rest. A mapped bone `b` gets the global
//! rotation `G_j · A_b · H_b`: `H_b` its rest global, `A_b` the smallest rotation that turns
//! its rest direction (towards its first mapped descendant) onto joint `j`'s (towards the
//! matching SMPL-X joint). Its direction therefore follows SMPL-X's bone exactly, whatever
//! its rest pose; its local axes stay the host's. Unmapped bones keep their rest local
//! rotation. The mapped root moves as SMPL-X's pelvis, scaled by the ratio of leg lengths
//! (hip to knee to ankle) so the feet do not slide. The object comes out scaled the same
//! way in the world, and in each hand bone's frame so that a host can attach it to the hand.
use crate::error::{Error, Result};
use crate::frame::{Frame, CG_BODY_JOINTS, CG_HAND_JOINTS, CG_NUM_JOINTS};
use crate::skeleton::{
    add, cross, dot, mat_mul, mat_vec, matrix_to_quaternion, norm, quaternion_to_matrix, rotation_between, scale, sub,
    transpose, Mat3, Vec3, IDENTITY, SMPLX_PARENTS,
};

/// The SMPL-X joint names, in joint order (the manifest's `skeleton.joint_names`).
pub const SMPLX_JOINT_NAMES: [&str; CG_NUM_JOINTS] = [
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "jaw",
    "left_eye_smplhf",
    "right_eye_smplhf",
    "left_index1",
    "left_index2",
    "left_index3",
    "left_middle1",
    "left_middle2",
    "left_middle3",
    "left_pinky1",
    "left_pinky2",
    "left_pinky3",
    "left_ring1",
    "left_ring2",
    "left_ring3",
    "left_thumb1",
    "left_thumb2",
    "left_thumb3",
    "right_index1",
    "right_index2",
    "right_index3",
    "right_middle1",
    "right_middle2",
    "right_middle3",
    "right_pinky1",
    "right_pinky2",
    "right_pinky3",
    "right_ring1",
    "right_ring2",
    "right_ring3",
    "right_thumb1",
    "right_thumb2",
    "right_thumb3",
];

const WRISTS: [usize; 2] = [20, 21];
/// Hip, knee, ankle of each leg (SMPL-X).
const LEGS: [[usize; 3]; 2] = [[1, 4, 7], [2, 5, 8]];
/// A rest rotation must be a unit quaternion within this.
const UNIT_TOLERANCE: f64 = 1e-3;

/// One bone of a host skeleton: its parent (`None`: a root) and its rest transform relative
/// to the parent (to the world for a root), in the engine's coordinate system and units.
#[derive(Clone, Debug, PartialEq)]
pub struct Bone {
    pub name: String,
    pub parent: Option<usize>,
    pub rest_translation: [f32; 3],
    /// Unit quaternion x, y, z, w.
    pub rest_rotation: [f32; 4],
}

/// A host skeleton: bones in any order (parents need not come first), one or more roots.
#[derive(Clone, Debug, PartialEq)]
pub struct HostSkeleton {
    pub bones: Vec<Bone>,
}

/// One bone's pose in a retargeted frame.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct cg_bone_pose {
    /// Relative to the parent bone (the world for a root): what a host sets as the bone's
    /// local transform. The translation is the rest one except on the moving root.
    pub local_translation: [f32; 3],
    /// Unit quaternion x, y, z, w.
    pub local_rotation: [f32; 4],
    /// In the world (the engine's coordinate system).
    pub world_position: [f32; 3],
    pub world_rotation: [f32; 4],
}

/// The object in a retargeted frame: in the world (scaled with the character) and in each
/// hand bone's frame, for a host that attaches it to the holding hand.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct cg_retarget_object {
    /// The object's origin and rotation (x, y, z, w) in the world.
    pub world_position: [f32; 3],
    pub world_rotation: [f32; 4],
    /// The object in the frame of the bone mapped to each wrist, [left, right] (zero and
    /// identity when that wrist is not mapped).
    pub in_hand_position: [[f32; 3]; 2],
    pub in_hand_rotation: [[f32; 4]; 2],
    /// The bone index of each hand, -1 when the wrist is not mapped.
    pub hand_bone: [i32; 2],
    /// The frame's contact flags: 1 while that hand holds the object.
    pub contact: [u8; 2],
    pub reserved: [u8; 6],
}

/// A ready map: SMPL-X joint name, host bone name.
pub type MapEntry = (&'static str, &'static str);

/// The maps that ship with the engine.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BuiltinMap {
    /// Unity's `HumanBodyBones` names (`Hips`, `LeftUpperArm`, ...): a Unity host names each
    /// bone of its Humanoid avatar by the `HumanBodyBones` value it is mapped to.
    UnityHumanoid,
    /// The UE5 Mannequin (`pelvis`, `spine_01`..`spine_05`, `upperarm_l`, ...).
    Ue5Mannequin,
    /// Mixamo rigs (`mixamorig:Hips`, `mixamorig:LeftArm`, ...).
    Mixamo,
}

/// A ready map's entries (SMPL-X joint, bone). Every SMPL-X body and finger joint the rig has
/// a bone for; jaw and eyes are left out.
pub fn builtin_map(which: BuiltinMap) -> &'static [MapEntry] {
    match which {
        BuiltinMap::UnityHumanoid => &UNITY,
        BuiltinMap::Ue5Mannequin => &UE5,
        BuiltinMap::Mixamo => &MIXAMO,
    }
}

static UNITY: [MapEntry; 52] = [
    ("pelvis", "Hips"),
    ("left_hip", "LeftUpperLeg"),
    ("right_hip", "RightUpperLeg"),
    ("spine1", "Spine"),
    ("left_knee", "LeftLowerLeg"),
    ("right_knee", "RightLowerLeg"),
    ("spine2", "Chest"),
    ("left_ankle", "LeftFoot"),
    ("right_ankle", "RightFoot"),
    ("spine3", "UpperChest"),
    ("left_foot", "LeftToes"),
    ("right_foot", "RightToes"),
    ("neck", "Neck"),
    ("left_collar", "LeftShoulder"),
    ("right_collar", "RightShoulder"),
    ("head", "Head"),
    ("left_shoulder", "LeftUpperArm"),
    ("right_shoulder", "RightUpperArm"),
    ("left_elbow", "LeftLowerArm"),
    ("right_elbow", "RightLowerArm"),
    ("left_wrist", "LeftHand"),
    ("right_wrist", "RightHand"),
    ("left_index1", "LeftIndexProximal"),
    ("left_index2", "LeftIndexIntermediate"),
    ("left_index3", "LeftIndexDistal"),
    ("left_middle1", "LeftMiddleProximal"),
    ("left_middle2", "LeftMiddleIntermediate"),
    ("left_middle3", "LeftMiddleDistal"),
    ("left_pinky1", "LeftLittleProximal"),
    ("left_pinky2", "LeftLittleIntermediate"),
    ("left_pinky3", "LeftLittleDistal"),
    ("left_ring1", "LeftRingProximal"),
    ("left_ring2", "LeftRingIntermediate"),
    ("left_ring3", "LeftRingDistal"),
    ("left_thumb1", "LeftThumbProximal"),
    ("left_thumb2", "LeftThumbIntermediate"),
    ("left_thumb3", "LeftThumbDistal"),
    ("right_index1", "RightIndexProximal"),
    ("right_index2", "RightIndexIntermediate"),
    ("right_index3", "RightIndexDistal"),
    ("right_middle1", "RightMiddleProximal"),
    ("right_middle2", "RightMiddleIntermediate"),
    ("right_middle3", "RightMiddleDistal"),
    ("right_pinky1", "RightLittleProximal"),
    ("right_pinky2", "RightLittleIntermediate"),
    ("right_pinky3", "RightLittleDistal"),
    ("right_ring1", "RightRingProximal"),
    ("right_ring2", "RightRingIntermediate"),
    ("right_ring3", "RightRingDistal"),
    ("right_thumb1", "RightThumbProximal"),
    ("right_thumb2", "RightThumbIntermediate"),
    ("right_thumb3", "RightThumbDistal"),
];

static UE5: [MapEntry; 52] = [
    ("pelvis", "pelvis"),
    ("left_hip", "thigh_l"),
    ("right_hip", "thigh_r"),
    ("spine1", "spine_01"),
    ("left_knee", "calf_l"),
    ("right_knee", "calf_r"),
    ("spine2", "spine_03"),
    ("left_ankle", "foot_l"),
    ("right_ankle", "foot_r"),
    ("spine3", "spine_05"),
    ("left_foot", "ball_l"),
    ("right_foot", "ball_r"),
    ("neck", "neck_01"),
    ("left_collar", "clavicle_l"),
    ("right_collar", "clavicle_r"),
    ("head", "head"),
    ("left_shoulder", "upperarm_l"),
    ("right_shoulder", "upperarm_r"),
    ("left_elbow", "lowerarm_l"),
    ("right_elbow", "lowerarm_r"),
    ("left_wrist", "hand_l"),
    ("right_wrist", "hand_r"),
    ("left_index1", "index_01_l"),
    ("left_index2", "index_02_l"),
    ("left_index3", "index_03_l"),
    ("left_middle1", "middle_01_l"),
    ("left_middle2", "middle_02_l"),
    ("left_middle3", "middle_03_l"),
    ("left_pinky1", "pinky_01_l"),
    ("left_pinky2", "pinky_02_l"),
    ("left_pinky3", "pinky_03_l"),
    ("left_ring1", "ring_01_l"),
    ("left_ring2", "ring_02_l"),
    ("left_ring3", "ring_03_l"),
    ("left_thumb1", "thumb_01_l"),
    ("left_thumb2", "thumb_02_l"),
    ("left_thumb3", "thumb_03_l"),
    ("right_index1", "index_01_r"),
    ("right_index2", "index_02_r"),
    ("right_index3", "index_03_r"),
    ("right_middle1", "middle_01_r"),
    ("right_middle2", "middle_02_r"),
    ("right_middle3", "middle_03_r"),
    ("right_pinky1", "pinky_01_r"),
    ("right_pinky2", "pinky_02_r"),
    ("right_pinky3", "pinky_03_r"),
    ("right_ring1", "ring_01_r"),
    ("right_ring2", "ring_02_r"),
    ("right_ring3", "ring_03_r"),
    ("right_thumb1", "thumb_01_r"),
    ("right_thumb2", "thumb_02_r"),
    ("right_thumb3", "thumb_03_r"),
];

static MIXAMO: [MapEntry; 52] = [
    ("pelvis", "mixamorig:Hips"),
    ("left_hip", "mixamorig:LeftUpLeg"),
    ("right_hip", "mixamorig:RightUpLeg"),
    ("spine1", "mixamorig:Spine"),
    ("left_knee", "mixamorig:LeftLeg"),
    ("right_knee", "mixamorig:RightLeg"),
    ("spine2", "mixamorig:Spine1"),
    ("left_ankle", "mixamorig:LeftFoot"),
    ("right_ankle", "mixamorig:RightFoot"),
    ("spine3", "mixamorig:Spine2"),
    ("left_foot", "mixamorig:LeftToeBase"),
    ("right_foot", "mixamorig:RightToeBase"),
    ("neck", "mixamorig:Neck"),
    ("left_collar", "mixamorig:LeftShoulder"),
    ("right_collar", "mixamorig:RightShoulder"),
    ("head", "mixamorig:Head"),
    ("left_shoulder", "mixamorig:LeftArm"),
    ("right_shoulder", "mixamorig:RightArm"),
    ("left_elbow", "mixamorig:LeftForeArm"),
    ("right_elbow", "mixamorig:RightForeArm"),
    ("left_wrist", "mixamorig:LeftHand"),
    ("right_wrist", "mixamorig:RightHand"),
    ("left_index1", "mixamorig:LeftHandIndex1"),
    ("left_index2", "mixamorig:LeftHandIndex2"),
    ("left_index3", "mixamorig:LeftHandIndex3"),
    ("left_middle1", "mixamorig:LeftHandMiddle1"),
    ("left_middle2", "mixamorig:LeftHandMiddle2"),
    ("left_middle3", "mixamorig:LeftHandMiddle3"),
    ("left_pinky1", "mixamorig:LeftHandPinky1"),
    ("left_pinky2", "mixamorig:LeftHandPinky2"),
    ("left_pinky3", "mixamorig:LeftHandPinky3"),
    ("left_ring1", "mixamorig:LeftHandRing1"),
    ("left_ring2", "mixamorig:LeftHandRing2"),
    ("left_ring3", "mixamorig:LeftHandRing3"),
    ("left_thumb1", "mixamorig:LeftHandThumb1"),
    ("left_thumb2", "mixamorig:LeftHandThumb2"),
    ("left_thumb3", "mixamorig:LeftHandThumb3"),
    ("right_index1", "mixamorig:RightHandIndex1"),
    ("right_index2", "mixamorig:RightHandIndex2"),
    ("right_index3", "mixamorig:RightHandIndex3"),
    ("right_middle1", "mixamorig:RightHandMiddle1"),
    ("right_middle2", "mixamorig:RightHandMiddle2"),
    ("right_middle3", "mixamorig:RightHandMiddle3"),
    ("right_pinky1", "mixamorig:RightHandPinky1"),
    ("right_pinky2", "mixamorig:RightHandPinky2"),
    ("right_pinky3", "mixamorig:RightHandPinky3"),
    ("right_ring1", "mixamorig:RightHandRing1"),
    ("right_ring2", "mixamorig:RightHandRing2"),
    ("right_ring3", "mixamorig:RightHandRing3"),
    ("right_thumb1", "mixamorig:RightHandThumb1"),
    ("right_thumb2", "mixamorig:RightHandThumb2"),
    ("right_thumb3", "mixamorig:RightHandThumb3"),
];

/// A host skeleton and map, checked and prepared; [`Retargeter::apply`] per frame.
#[derive(Clone, Debug)]
pub struct Retargeter {
    bones: Vec<Bone>,
    /// Bones with every parent before its child.
    order: Vec<usize>,
    /// The SMPL-X joint each bone follows.
    joint: Vec<Option<usize>>,
    /// `A_b · H_b` of each mapped bone (identity for the others).
    offset: Vec<Mat3>,
    rest_local: Vec<Mat3>,
    rest_position: Vec<Vec3>,
    /// The bone that moves as the pelvis (the mapped pelvis, else the first root).
    root: usize,
    /// Host leg length / SMPL-X leg length.
    scale: f64,
    /// SMPL-X rest joints, and the `rest_position` of the root bone.
    smplx_rest: [Vec3; CG_NUM_JOINTS],
    hands: [Option<usize>; 2],
}

/// The rotation whose columns are `a` normalized, the part of `b` orthogonal to it, and
/// their cross product.
fn frame_of(a: &Vec3, b: &Vec3) -> Mat3 {
    let e1 = scale(a, 1.0 / norm(a));
    let r = sub(b, &scale(&e1, dot(&e1, b)));
    let e2 = scale(&r, 1.0 / norm(&r));
    let e3 = cross(&e1, &e2);
    [[e1[0], e2[0], e3[0]], [e1[1], e2[1], e3[1]], [e1[2], e2[2], e3[2]]]
}

fn invalid(msg: String) -> Error {
    Error::InvalidArgument(format!("retargeting: {msg}"))
}

fn quat(q: &[f32; 4]) -> [f64; 4] {
    q.map(f64::from)
}

fn to_f32<const N: usize>(v: &[f64; N]) -> [f32; N] {
    v.map(|x| x as f32)
}

impl Retargeter {
    /// `smplx_rest`: the engine's rest joints in its coordinate system and units
    /// (`Engine::rest_joints`); `map`: (SMPL-X joint name, bone name) pairs. Errors
    /// ([`Error::InvalidArgument`]) name the bone or entry: an empty or duplicate bone name, a
    /// parent out of range or a cycle, a non-finite value or a non-unit rest rotation, a map
    /// entry naming an unknown joint or bone, a joint or bone mapped twice, a map that
    /// leaves a mapped bone's parent chain inconsistent with SMPL-X's (a bone mapped to a
    /// joint whose nearest mapped ancestor bone follows a joint that is not its ancestor).
    pub fn new(smplx_rest: &[[f32; 3]; CG_NUM_JOINTS], skeleton: HostSkeleton, map: &[(&str, &str)]) -> Result<Self> {
        let bones = skeleton.bones;
        let n = bones.len();
        if n == 0 {
            return Err(invalid("the skeleton has no bones".into()));
        }
        let mut by_name = std::collections::HashMap::with_capacity(n);
        for (i, b) in bones.iter().enumerate() {
            if b.name.is_empty() {
                return Err(invalid(format!("bone {i} has an empty name")));
            }
            if let Some(j) = by_name.insert(b.name.as_str(), i) {
                return Err(invalid(format!("bones {j} and {i} are both named {:?}", b.name)));
            }
            if let Some(p) = b.parent {
                if p >= n || p == i {
                    return Err(invalid(format!("bone {:?} has parent {p}, not another of the {n} bones", b.name)));
                }
            }
            if !b.rest_translation.iter().chain(&b.rest_rotation).all(|v| v.is_finite()) {
                return Err(invalid(format!("bone {:?} has a non-finite rest transform", b.name)));
            }
            let q = quat(&b.rest_rotation);
            let len = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            if (len - 1.0).abs() > UNIT_TOLERANCE {
                return Err(invalid(format!(
                    "bone {:?}: rest rotation is not a unit quaternion (|q| = {len})",
                    b.name
                )));
            }
        }
        // Parents first: depth by walking up, at most n steps (more is a cycle).
        let mut depth = vec![0usize; n];
        for (i, d) in depth.iter_mut().enumerate() {
            let mut at = i;
            while let Some(p) = bones[at].parent {
                *d += 1;
                at = p;
                if *d > n {
                    return Err(invalid(format!("bone {:?} is in a parent cycle", bones[i].name)));
                }
            }
        }
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by_key(|&i| (depth[i], i));

        let mut joint = vec![None; n];
        let mut bone_of = [None; CG_NUM_JOINTS];
        for &(j, b) in map {
            let ji = SMPLX_JOINT_NAMES
                .iter()
                .position(|&x| x == j)
                .ok_or_else(|| invalid(format!("map entry ({j:?}, {b:?}): {j:?} is not an SMPL-X joint")))?;
            let bi = *by_name
                .get(b)
                .ok_or_else(|| invalid(format!("map entry ({j:?}, {b:?}): the skeleton has no bone {b:?}")))?;
            if let Some(other) = joint[bi] {
                return Err(invalid(format!("bone {b:?} is mapped twice ({:?} and {j:?})", SMPLX_JOINT_NAMES[other])));
            }
            if bone_of[ji].is_some() {
                return Err(invalid(format!("SMPL-X joint {j:?} is mapped twice")));
            }
            joint[bi] = Some(ji);
            bone_of[ji] = Some(bi);
        }
        if bone_of.iter().all(Option::is_none) {
            return Err(invalid("the map names no bone of the skeleton".into()));
        }

        // Rest globals.
        let mut rest_local = vec![IDENTITY; n];
        let mut rest_global = vec![IDENTITY; n];
        let mut rest_position = vec![[0.0; 3]; n];
        for &i in &order {
            let b = &bones[i];
            let q = quat(&b.rest_rotation);
            let len = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            rest_local[i] = quaternion_to_matrix(&q.map(|v| v / len));
            let t = b.rest_translation.map(f64::from);
            (rest_global[i], rest_position[i]) = match b.parent {
                Some(p) => {
                    (mat_mul(&rest_global[p], &rest_local[i]), add(&rest_position[p], &mat_vec(&rest_global[p], &t)))
                }
                None => (rest_local[i], t),
            };
        }
        let smplx: [Vec3; CG_NUM_JOINTS] = std::array::from_fn(|j| smplx_rest[j].map(f64::from));

        // Each mapped bone's alignment: its rest direction onto its joint's, both towards the
        // first mapped descendant bone whose joint descends from the bone's joint.
        let descends = |mut k: usize, j: usize| {
            while k != j {
                let p = SMPLX_PARENTS[k];
                if p < 0 {
                    return false;
                }
                k = p as usize;
            }
            true
        };
        let mut children = vec![Vec::new(); n];
        for &i in &order {
            if let Some(p) = bones[i].parent {
                children[p].push(i);
            }
        }
        let mut offset = vec![IDENTITY; n];
        for b in 0..n {
            let Some(j) = joint[b] else { continue };
            // Breadth-first over b's descendants: the nearest mapped ones below j, each with
            // its rest direction from b (host) and from j (SMPL-X).
            let mut queue = std::collections::VecDeque::from(children[b].clone());
            let mut dirs: Vec<(Vec3, Vec3)> = Vec::new();
            while let Some(c) = queue.pop_front() {
                match joint[c] {
                    Some(k) if k != j && descends(k, j) => {
                        dirs.push((sub(&rest_position[c], &rest_position[b]), sub(&smplx[k], &smplx[j])));
                    }
                    _ => queue.extend(children[c].iter().copied()),
                }
            }
            let align = match dirs.first() {
                Some((h, s)) => {
                    // A second direction not parallel to the first fixes the twist about it
                    // (a hand's fingers, a pelvis's hips and spine); else the smallest swing.
                    let second = dirs[1..].iter().find(|(h2, s2)| {
                        let (a, b) = (cross(h, h2), cross(s, s2));
                        norm(&a) > 0.1 * norm(h) * norm(h2) && norm(&b) > 0.1 * norm(s) * norm(s2)
                    });
                    match second {
                        Some((h2, s2)) => mat_mul(&frame_of(s, s2), &transpose(&frame_of(h, h2))),
                        None => rotation_between(h, s),
                    }
                }
                None => IDENTITY,
            };
            offset[b] = mat_mul(&align, &rest_global[b]);
        }
        // A leaf keeps its parent's alignment (a fingertip bends as its finger).
        for &b in &order {
            if let (Some(_), Some(p)) = (joint[b], bones[b].parent) {
                let leaf = !children[b].iter().any(|&c| joint[c].is_some());
                if leaf && joint[p].is_some() {
                    let parent_align = mat_mul(&offset[p], &transpose(&rest_global[p]));
                    offset[b] = mat_mul(&parent_align, &rest_global[b]);
                }
            }
        }

        let root = bone_of[0].unwrap_or(order[0]);
        let leg = |pos: &dyn Fn(usize) -> Option<Vec3>| -> Option<f64> {
            let mut total = 0.0;
            let mut legs = 0;
            for [h, k, a] in LEGS {
                if let (Some(ph), Some(pk), Some(pa)) = (pos(h), pos(k), pos(a)) {
                    total += norm(&sub(&pk, &ph)) + norm(&sub(&pa, &pk));
                    legs += 1;
                }
            }
            (legs > 0).then(|| total / legs as f64)
        };
        let host_leg = leg(&|j| bone_of[j].map(|b| rest_position[b]));
        let smplx_leg = leg(&|j| Some(smplx[j]));
        let scale = match (host_leg, smplx_leg) {
            (Some(h), Some(s)) if h > 0.0 && s > 0.0 => h / s,
            _ => 1.0,
        };
        Ok(Retargeter {
            hands: WRISTS.map(|w| bone_of[w]),
            bones,
            order,
            joint,
            offset,
            rest_local,
            rest_position,
            root,
            scale,
            smplx_rest: smplx,
        })
    }

    /// With a ready map: its entries whose bone the skeleton lacks are skipped (an avatar
    /// without an upper chest, toes or some fingers), the rest as [`Self::new`].
    pub fn with_builtin(
        smplx_rest: &[[f32; 3]; CG_NUM_JOINTS],
        skeleton: HostSkeleton,
        which: BuiltinMap,
    ) -> Result<Self> {
        let map: Vec<MapEntry> =
            builtin_map(which).iter().copied().filter(|(_, b)| skeleton.bones.iter().any(|x| x.name == *b)).collect();
        Retargeter::new(smplx_rest, skeleton, &map)
    }

    /// The skeleton's bones, in the host's order (the order of [`Self::apply`]'s output).
    pub fn bones(&self) -> &[Bone] {
        &self.bones
    }

    /// Host leg length over SMPL-X's: the factor on root motion and the object's position.
    pub fn scale(&self) -> f64 {
        self.scale
    }

    /// Poses every bone for one engine frame (`out.len()` = the number of bones, in the
    /// skeleton's order) and, when asked, the object. No allocation.
    ///
    /// Panics if `out` has the wrong length (the C ABI checks it first).
    pub fn apply(&self, frame: &Frame, out: &mut [cg_bone_pose], object: Option<&mut cg_retarget_object>) {
        assert_eq!(out.len(), self.bones.len(), "one pose per bone");
        // SMPL-X FK from the frame's local rotations.
        let mut local = [IDENTITY; CG_NUM_JOINTS];
        local[0] = quaternion_to_matrix(&quat(&frame.root_rotation));
        for i in 0..CG_BODY_JOINTS {
            local[1 + i] = quaternion_to_matrix(&quat(&frame.body_rotations[i]));
        }
        for i in 0..CG_HAND_JOINTS {
            local[25 + i] = quaternion_to_matrix(&quat(&frame.left_hand_rotations[i]));
            local[40 + i] = quaternion_to_matrix(&quat(&frame.right_hand_rotations[i]));
        }
        let mut global = [IDENTITY; CG_NUM_JOINTS];
        global[0] = local[0];
        for j in 1..CG_NUM_JOINTS {
            global[j] = mat_mul(&global[SMPLX_PARENTS[j] as usize], &local[j]);
        }
        let pelvis = frame.root_translation.map(f64::from);
        let moved = |p: &Vec3| add(&self.rest_position[self.root], &scale(&sub(p, &self.smplx_rest[0]), self.scale));

        // Bones, parents first (a parent's world transform is read back from `out`).
        for &b in &self.order {
            let parent = self.bones[b].parent.map(|p| {
                let r = &out[p];
                (quaternion_to_matrix(&quat(&r.world_rotation)), r.world_position.map(f64::from))
            });
            let (pg, pp) = parent.unwrap_or((IDENTITY, [0.0; 3]));
            let g = match self.joint[b] {
                Some(j) => mat_mul(&global[j], &self.offset[b]),
                None => mat_mul(&pg, &self.rest_local[b]),
            };
            let local_rot = mat_mul(&transpose(&pg), &g);
            let rest_t = self.bones[b].rest_translation.map(f64::from);
            let (position, local_t) = if b == self.root {
                let p = moved(&pelvis);
                (p, mat_vec(&transpose(&pg), &sub(&p, &pp)))
            } else {
                (add(&pp, &mat_vec(&pg, &rest_t)), rest_t)
            };
            out[b] = cg_bone_pose {
                local_translation: to_f32(&local_t),
                local_rotation: to_f32(&matrix_to_quaternion(&local_rot)),
                world_position: to_f32(&position),
                world_rotation: to_f32(&matrix_to_quaternion(&g)),
            };
        }

        if let Some(o) = object {
            let rot = quaternion_to_matrix(&quat(&frame.object_rotation));
            let pos = frame.object_translation.map(f64::from);
            // SMPL-X FK for the wrists' positions.
            let mut p = [[0.0; 3]; CG_NUM_JOINTS];
            p[0] = pelvis;
            for j in 1..CG_NUM_JOINTS {
                let q = SMPLX_PARENTS[j] as usize;
                p[j] = add(&p[q], &mat_vec(&global[q], &sub(&self.smplx_rest[j], &self.smplx_rest[q])));
            }
            o.world_position = to_f32(&moved(&pos));
            o.world_rotation = to_f32(&matrix_to_quaternion(&rot));
            for (h, &w) in WRISTS.iter().enumerate() {
                // The object in the wrist's frame, scaled; then in the hand bone's frame
                // (its world rotation is the wrist's times the bone's offset).
                let rel_t = scale(&mat_vec(&transpose(&global[w]), &sub(&pos, &p[w])), self.scale);
                let rel_r = mat_mul(&transpose(&global[w]), &rot);
                match self.hands[h] {
                    Some(b) => {
                        let inv = transpose(&self.offset[b]);
                        o.in_hand_position[h] = to_f32(&mat_vec(&inv, &rel_t));
                        o.in_hand_rotation[h] = to_f32(&matrix_to_quaternion(&mat_mul(&inv, &rel_r)));
                        o.hand_bone[h] = b as i32;
                    }
                    None => {
                        o.in_hand_position[h] = [0.0; 3];
                        o.in_hand_rotation[h] = [0.0, 0.0, 0.0, 1.0];
                        o.hand_bone[h] = -1;
                    }
                }
            }
            o.contact = frame.contact;
            o.reserved = [0; 6];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampler::SplitMix64;
    use crate::skeleton::tests::random_rotation;
    use crate::skeleton::{axis_angle, Skeleton};

    /// A rest skeleton with human proportions (metres; y up, arms along ±x).
    fn rest() -> [[f32; 3]; CG_NUM_JOINTS] {
        let mut r = [[0.0f32; 3]; CG_NUM_JOINTS];
        let body: [(usize, [f32; 3]); 22] = [
            (0, [0.0, 0.95, 0.0]),
            (1, [0.08, 0.88, 0.0]),
            (2, [-0.08, 0.88, 0.0]),
            (3, [0.0, 1.05, 0.0]),
            (4, [0.09, 0.5, 0.0]),
            (5, [-0.09, 0.5, 0.0]),
            (6, [0.0, 1.18, 0.0]),
            (7, [0.09, 0.1, 0.0]),
            (8, [-0.09, 0.1, 0.0]),
            (9, [0.0, 1.3, 0.0]),
            (10, [0.09, 0.02, 0.12]),
            (11, [-0.09, 0.02, 0.12]),
            (12, [0.0, 1.5, 0.0]),
            (13, [0.07, 1.42, 0.0]),
            (14, [-0.07, 1.42, 0.0]),
            (15, [0.0, 1.62, 0.02]),
            (16, [0.18, 1.42, 0.0]),
            (17, [-0.18, 1.42, 0.0]),
            (18, [0.45, 1.42, 0.0]),
            (19, [-0.45, 1.42, 0.0]),
            (20, [0.7, 1.42, 0.0]),
            (21, [-0.7, 1.42, 0.0]),
        ];
        for (j, p) in body {
            r[j] = p;
        }
        r[22] = [0.0, 1.58, 0.05];
        r[23] = [0.03, 1.65, 0.07];
        r[24] = [-0.03, 1.65, 0.07];
        // fingers: five rays of three segments out of each wrist
        for (side, sign) in [(0usize, 1.0f32), (1, -1.0)] {
            let w = r[20 + side];
            for f in 0..5 {
                for k in 0..3 {
                    let j = 25 + 15 * side + 3 * f + k;
                    let z = if f == 4 { 0.03 } else { 0.02 * (f as f32 - 1.5) };
                    r[j] = [w[0] + sign * (0.06 + 0.025 * k as f32), w[1] - 0.01 * (f == 4) as i32 as f32, w[2] + z];
                }
            }
        }
        r
    }

    fn smplx_host(scale_by: f32) -> HostSkeleton {
        let r = rest();
        HostSkeleton {
            bones: (0..CG_NUM_JOINTS)
                .map(|j| {
                    let p = SMPLX_PARENTS[j];
                    let t = if p < 0 { r[j] } else { std::array::from_fn(|i| r[j][i] - r[p as usize][i]) };
                    Bone {
                        name: SMPLX_JOINT_NAMES[j].to_string(),
                        parent: (p >= 0).then_some(p as usize),
                        rest_translation: t.map(|v| v * scale_by),
                        rest_rotation: [0.0, 0.0, 0.0, 1.0],
                    }
                })
                .collect(),
        }
    }

    fn identity_map() -> Vec<(&'static str, &'static str)> {
        SMPLX_JOINT_NAMES.iter().map(|&n| (n, n)).collect()
    }

    /// A frame with random joint rotations (bounded so it is a plausible pose) and its FK.
    fn frame(seed: u64) -> (Frame, [Vec3; CG_NUM_JOINTS]) {
        let mut rng = SplitMix64::new(seed);
        let mut f = Frame::default();
        let mut local = [IDENTITY; CG_NUM_JOINTS];
        for (j, l) in local.iter_mut().enumerate() {
            if !(22..25).contains(&j) {
                *l = random_rotation(&mut rng);
            }
        }
        let q = |m: &Mat3| to_f32(&matrix_to_quaternion(m));
        f.root_rotation = q(&local[0]);
        for i in 0..CG_BODY_JOINTS {
            f.body_rotations[i] = q(&local[1 + i]);
        }
        for i in 0..CG_HAND_JOINTS {
            f.left_hand_rotations[i] = q(&local[25 + i]);
            f.right_hand_rotations[i] = q(&local[40 + i]);
        }
        f.root_translation = [0.3, 0.9, -0.2];
        f.object_translation = [0.5, 1.1, 0.3];
        f.object_rotation = q(&random_rotation(&mut rng));
        f.contact = [0, 1];
        // FK of the same (f32-rounded) rotations
        for (j, l) in local.iter_mut().enumerate() {
            let qq = match j {
                0 => f.root_rotation,
                1..=21 => f.body_rotations[j - 1],
                25..=39 => f.left_hand_rotations[j - 25],
                40..=54 => f.right_hand_rotations[j - 40],
                _ => [0.0, 0.0, 0.0, 1.0],
            };
            *l = quaternion_to_matrix(&quat(&qq));
        }
        let s = Skeleton::new(&SMPLX_PARENTS, &rest()).unwrap();
        let (mut g, mut p) = ([IDENTITY; CG_NUM_JOINTS], [[0.0; 3]; CG_NUM_JOINTS]);
        s.forward(&local, f.root_translation.map(f64::from), &mut g, &mut p);
        (f, p)
    }

    fn dist(a: &[f32; 3], b: &Vec3) -> f64 {
        norm(&sub(&a.map(f64::from), b))
    }

    #[test]
    fn the_smplx_skeleton_round_trips() {
        let r = Retargeter::new(&rest(), smplx_host(1.0), &identity_map()).unwrap();
        assert!((r.scale() - 1.0).abs() < 1e-6);
        let mut out = vec![cg_bone_pose::default(); CG_NUM_JOINTS];
        for seed in 1..5 {
            let (f, p) = frame(seed);
            r.apply(&f, &mut out, None);
            for j in 0..CG_NUM_JOINTS {
                assert!(dist(&out[j].world_position, &p[j]) < 1e-3, "joint {j}: {:?} vs {:?}", out[j], p[j]);
            }
            // the local rotations are the frame's own
            assert!(out[18].local_rotation.iter().zip(&f.body_rotations[17]).all(|(a, b)| (a - b).abs() < 1e-5));
        }
    }

    #[test]
    fn a_rescaled_skeleton_moves_the_same_up_to_scale() {
        let r = Retargeter::new(&rest(), smplx_host(1.3), &identity_map()).unwrap();
        assert!((r.scale() - 1.3).abs() < 1e-6);
        let mut out = vec![cg_bone_pose::default(); CG_NUM_JOINTS];
        let mut obj = cg_retarget_object::default();
        let (f, p) = frame(7);
        r.apply(&f, &mut out, Some(&mut obj));
        for j in 0..CG_NUM_JOINTS {
            assert!(dist(&out[j].world_position, &scale(&p[j], 1.3)) < 1.3e-3, "joint {j}");
        }
        // The object: in the world scaled, and where each hand bone says it is.
        let o = scale(&f.object_translation.map(f64::from), 1.3);
        assert!(dist(&obj.world_position, &o) < 1e-4);
        for (h, &wrist) in WRISTS.iter().enumerate() {
            let b = obj.hand_bone[h] as usize;
            assert_eq!(b, wrist);
            let g = quaternion_to_matrix(&quat(&out[b].world_rotation));
            let at = add(&out[b].world_position.map(f64::from), &mat_vec(&g, &obj.in_hand_position[h].map(f64::from)));
            assert!(dist(&obj.world_position, &at) < 1e-4, "hand {h}");
        }
        assert_eq!(obj.contact, [0, 1]);
    }

    /// The SMPL-X skeleton in an A-pose (arms 45° down) with every bone's local axes turned
    /// at random, built from world rest transforms as a DCC tool would export it.
    fn a_pose_host(seed: u64) -> HostSkeleton {
        let r = rest().map(|p| p.map(f64::from));
        let mut rng = SplitMix64::new(seed);
        let down = [axis_angle(&[0.0, 0.0, 1.0], -0.785), axis_angle(&[0.0, 0.0, 1.0], 0.785)];
        let arm = |j: usize| -> Option<usize> {
            let mut k = j;
            loop {
                if k == 16 || k == 17 {
                    return Some(k - 16);
                }
                let p = SMPLX_PARENTS[k];
                if p < 0 {
                    return None;
                }
                k = p as usize;
            }
        };
        let pos: Vec<Vec3> = (0..CG_NUM_JOINTS)
            .map(|j| match arm(j) {
                Some(side) => add(&r[16 + side], &mat_vec(&down[side], &sub(&r[j], &r[16 + side]))),
                None => r[j],
            })
            .collect();
        let axes: Vec<Mat3> = (0..CG_NUM_JOINTS).map(|_| random_rotation(&mut rng)).collect();
        HostSkeleton {
            bones: (0..CG_NUM_JOINTS)
                .map(|j| {
                    let p = SMPLX_PARENTS[j];
                    let (t, l) = if p < 0 {
                        (pos[j], axes[j])
                    } else {
                        let pg = &axes[p as usize];
                        (mat_vec(&transpose(pg), &sub(&pos[j], &pos[p as usize])), mat_mul(&transpose(pg), &axes[j]))
                    };
                    Bone {
                        name: format!("bone_{}", SMPLX_JOINT_NAMES[j]),
                        parent: (p >= 0).then_some(p as usize),
                        rest_translation: to_f32(&t),
                        rest_rotation: to_f32(&matrix_to_quaternion(&l)),
                    }
                })
                .collect(),
        }
    }

    #[test]
    fn another_rest_pose_and_axis_convention_gives_the_same_bone_directions() {
        let names: Vec<String> = SMPLX_JOINT_NAMES.iter().map(|n| format!("bone_{n}")).collect();
        let map: Vec<(&str, &str)> = SMPLX_JOINT_NAMES.iter().zip(&names).map(|(a, b)| (*a, b.as_str())).collect();
        let r = Retargeter::new(&rest(), a_pose_host(3), &map).unwrap();
        let mut out = vec![cg_bone_pose::default(); CG_NUM_JOINTS];
        for seed in 10..14 {
            let (f, p) = frame(seed);
            r.apply(&f, &mut out, None);
            for j in 1..CG_NUM_JOINTS {
                let q = SMPLX_PARENTS[j] as usize;
                let want = sub(&p[j], &p[q]);
                let got = sub(&out[j].world_position.map(f64::from), &out[q].world_position.map(f64::from));
                let cos = dot(&want, &got) / (norm(&want) * norm(&got));
                let deg = cos.clamp(-1.0, 1.0).acos().to_degrees();
                assert!(deg < 2.0, "bone {} -> {}: {deg:.2}°", SMPLX_JOINT_NAMES[q], SMPLX_JOINT_NAMES[j]);
            }
        }
    }

    #[test]
    fn unmapped_bones_stay_at_rest_and_builtin_maps_are_well_formed() {
        for which in [BuiltinMap::UnityHumanoid, BuiltinMap::Ue5Mannequin, BuiltinMap::Mixamo] {
            let m = builtin_map(which);
            assert_eq!(m.len(), 52);
            let mut joints: Vec<&str> = m.iter().map(|e| e.0).collect();
            let mut bones: Vec<&str> = m.iter().map(|e| e.1).collect();
            joints.sort_unstable();
            joints.dedup();
            bones.sort_unstable();
            bones.dedup();
            assert_eq!((joints.len(), bones.len()), (52, 52), "{which:?}");
            assert!(joints.iter().all(|j| SMPLX_JOINT_NAMES.contains(j)), "{which:?}");
        }
        // The SMPL-X skeleton named as the UE5 Mannequin, plus its two extra spine bones
        // (spine_02, spine_04) and a root at the floor, none of them mapped.
        let mut host = smplx_host(1.0);
        for (j, b) in builtin_map(BuiltinMap::Ue5Mannequin) {
            let i = SMPLX_JOINT_NAMES.iter().position(|n| n == j).unwrap();
            host.bones[i].name = b.to_string();
        }
        let n = host.bones.len();
        host.bones.push(Bone {
            name: "root".into(),
            parent: None,
            rest_translation: [0.0; 3],
            rest_rotation: [0.0, 0.0, 0.0, 1.0],
        });
        let pelvis = host.bones[0].rest_translation;
        host.bones[0].parent = Some(n);
        host.bones[0].rest_translation = pelvis;
        let r = Retargeter::new(&rest(), host, builtin_map(BuiltinMap::Ue5Mannequin)).unwrap();
        let mut out = vec![cg_bone_pose::default(); n + 1];
        let (f, p) = frame(5);
        r.apply(&f, &mut out, None);
        assert_eq!(out[n].local_rotation, [0.0, 0.0, 0.0, 1.0], "root stays at rest");
        assert_eq!(out[n].world_position, [0.0; 3]);
        for j in 0..22 {
            assert!(dist(&out[j].world_position, &p[j]) < 1e-3, "joint {j}");
        }
        // jaw and eyes are not in the map: they keep their rest local rotation
        assert_eq!(out[22].local_rotation, [0.0, 0.0, 0.0, 1.0]);
    }

    #[test]
    fn bad_skeletons_and_maps_are_errors_that_say_what() {
        let bone = |name: &str, parent: Option<usize>| Bone {
            name: name.into(),
            parent,
            rest_translation: [0.0, 0.1, 0.0],
            rest_rotation: [0.0, 0.0, 0.0, 1.0],
        };
        let ok_map = [("pelvis", "a")];
        let cases: Vec<(Vec<Bone>, Vec<(&str, &str)>, &str)> = vec![
            (vec![], ok_map.to_vec(), "no bones"),
            (vec![bone("", None)], ok_map.to_vec(), "empty name"),
            (vec![bone("a", None), bone("a", Some(0))], ok_map.to_vec(), "both named \"a\""),
            (vec![bone("a", Some(1)), bone("b", Some(0))], ok_map.to_vec(), "parent cycle"),
            (vec![bone("a", Some(5))], ok_map.to_vec(), "has parent 5"),
            (vec![bone("a", Some(0))], ok_map.to_vec(), "has parent 0"),
            (
                vec![Bone { rest_rotation: [0.0, 0.0, 0.0, 2.0], ..bone("a", None) }],
                ok_map.to_vec(),
                "not a unit quaternion",
            ),
            (vec![Bone { rest_translation: [f32::NAN, 0.0, 0.0], ..bone("a", None) }], ok_map.to_vec(), "non-finite"),
            (vec![bone("a", None)], vec![("pelvis", "b")], "no bone \"b\""),
            (vec![bone("a", None)], vec![("tail", "a")], "\"tail\" is not an SMPL-X joint"),
            (vec![bone("a", None)], vec![("pelvis", "a"), ("spine1", "a")], "mapped twice"),
            (vec![bone("a", None), bone("b", Some(0))], vec![("pelvis", "a"), ("pelvis", "b")], "mapped twice"),
            (vec![bone("a", None)], vec![], "names no bone"),
        ];
        for (bones, map, needle) in cases {
            let e = Retargeter::new(&rest(), HostSkeleton { bones }, &map).unwrap_err().to_string();
            assert!(e.contains(needle), "{needle:?} not in {e:?}");
            assert!(e.starts_with("invalid argument: retargeting: ") || e.contains("retargeting: "), "{e}");
        }
    }
}
