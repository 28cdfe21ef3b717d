//! Retargeting functions: a host skeleton and map in, one pose per bone out (docs/retargeting.md).
use std::ffi::{c_char, CString};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, OnceLock};

use super::engine::lookup_engine;
use super::handle::{Registry, TAG_RETARGETER};
use super::panic::{boundary, Failure};
use super::status::cg_status;
use crate::frame::cg_frame;
use crate::retarget::{builtin_map, cg_bone_pose, cg_retarget_object, Bone, BuiltinMap, HostSkeleton, Retargeter};

/// A host skeleton and map prepared for retargeting (`cg_retargeter_create`). Opaque.
pub struct cg_retargeter {
    _private: [u8; 0],
}

#[allow(dead_code)]
fn _assert_send_sync() {
    fn is_send_sync<T: Send + Sync>() {}
    is_send_sync::<RetargeterEntry>();
}

/// One bone of the host's skeleton. `rest_translation` / `rest_rotation` (unit quaternion
/// x, y, z, w) are relative to the parent bone (to the world for a root), in the engine's
/// coordinate system and units, in the pose the character is modelled in (T, A or other).
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct cg_bone_desc {
    /// NUL-terminated UTF-8, unique, at most `CG_BONE_NAME_MAX` bytes.
    pub name: *const c_char,
    /// Index of the parent bone in the same array, -1 for a root.
    pub parent: i32,
    /// Rest position relative to the parent.
    pub rest_translation: [f32; 3],
    /// Rest rotation relative to the parent, unit quaternion x, y, z, w.
    pub rest_rotation: [f32; 4],
}

/// One map entry: which bone follows which SMPL-X joint (`pelvis`, `left_wrist`,
/// `right_index1`, ...: the manifest's `skeleton.joint_names`).
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct cg_bone_map_entry {
    /// The SMPL-X joint's name, NUL-terminated.
    pub smplx_joint: *const c_char,
    /// The host bone's name, NUL-terminated.
    pub bone: *const c_char,
}

/// The maps that ship with the engine (`cg_builtin_map_entry`, `cg_retargeter_create_builtin`).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum cg_builtin_map {
    /// Unity's `HumanBodyBones` names (`Hips`, `LeftUpperArm`, `LeftIndexProximal`, ...).
    CG_MAP_UNITY_HUMANOID = 1,
    /// The UE5 Mannequin (`pelvis`, `spine_01`, `upperarm_l`, `index_01_l`, ...).
    CG_MAP_UE5_MANNEQUIN = 2,
    /// Mixamo rigs (`mixamorig:Hips`, `mixamorig:LeftArm`, ...).
    CG_MAP_MIXAMO = 3,
}

/// Longest bone or joint name, in bytes without the NUL.
pub const CG_BONE_NAME_MAX: usize = 255;
/// Most bones a skeleton may have (and map entries a map).
pub const CG_MAX_BONES: usize = 4096;

pub(crate) struct RetargeterEntry {
    retargeter: Retargeter,
    poisoned: AtomicBool,
}

pub(crate) static RETARGETERS: Registry<RetargeterEntry> = Registry::new(TAG_RETARGETER);

fn null(what: &str) -> Failure {
    Failure::new(cg_status::CG_ERR_NULL_POINTER, format_args!("{what} is NULL"))
}

fn invalid(msg: impl std::fmt::Display) -> Failure {
    Failure::new(cg_status::CG_ERR_INVALID_ARGUMENT, msg)
}

/// A NUL-terminated name, read at most `CG_BONE_NAME_MAX + 1` bytes far.
///
/// # Safety
/// `p` is NULL or points to readable bytes up to a NUL or that bound.
unsafe fn name<'a>(p: *const c_char, what: &dyn Fn() -> String) -> Result<&'a str, Failure> {
    if p.is_null() {
        return Err(null(&what()));
    }
    let mut len = 0;
    while unsafe { *p.add(len) } != 0 {
        len += 1;
        if len > CG_BONE_NAME_MAX {
            return Err(invalid(format_args!("{} is longer than {CG_BONE_NAME_MAX} bytes", what())));
        }
    }
    let bytes = unsafe { std::slice::from_raw_parts(p.cast::<u8>(), len) };
    std::str::from_utf8(bytes)
        .map_err(|_| Failure::new(cg_status::CG_ERR_INVALID_UTF8, format_args!("{} is not UTF-8", what())))
}

fn which_map(which: cg_builtin_map) -> BuiltinMap {
    match which {
        cg_builtin_map::CG_MAP_UNITY_HUMANOID => BuiltinMap::UnityHumanoid,
        cg_builtin_map::CG_MAP_UE5_MANNEQUIN => BuiltinMap::Ue5Mannequin,
        cg_builtin_map::CG_MAP_MIXAMO => BuiltinMap::Mixamo,
    }
}

/// The enum arrives as a plain int from C: anything else is an error, not UB.
fn read_map(which: i32) -> Result<cg_builtin_map, Failure> {
    match which {
        1 => Ok(cg_builtin_map::CG_MAP_UNITY_HUMANOID),
        2 => Ok(cg_builtin_map::CG_MAP_UE5_MANNEQUIN),
        3 => Ok(cg_builtin_map::CG_MAP_MIXAMO),
        v => Err(invalid(format_args!("which: {v} is not a cg_builtin_map"))),
    }
}

/// The ready maps as C strings, made once.
fn c_maps() -> &'static [Vec<(CString, CString)>; 3] {
    static MAPS: OnceLock<[Vec<(CString, CString)>; 3]> = OnceLock::new();
    MAPS.get_or_init(|| {
        [BuiltinMap::UnityHumanoid, BuiltinMap::Ue5Mannequin, BuiltinMap::Mixamo].map(|m| {
            builtin_map(m)
                .iter()
                .map(|(j, b)| (CString::new(*j).expect("no NUL in names"), CString::new(*b).expect("no NUL in names")))
                .collect()
        })
    })
}

/// Writes the number of entries of a ready map to `*count`. Errors: `CG_ERR_NULL_POINTER`,
/// `CG_ERR_INVALID_ARGUMENT` (not a `cg_builtin_map`). Any thread.
#[no_mangle]
pub unsafe extern "C" fn cg_builtin_map_size(which: i32, count: *mut usize) -> cg_status {
    boundary("cg_builtin_map_size", || {
        if count.is_null() {
            return Err(null("count"));
        }
        let m = which_map(read_map(which)?);
        unsafe { count.write(builtin_map(m).len()) };
        Ok(cg_status::CG_OK)
    })
}

/// Entry `index` of a ready map: the SMPL-X joint and the bone name that follows it
/// (static NUL-terminated strings, valid for the life of the process). Errors:
/// `CG_ERR_NULL_POINTER`, `CG_ERR_INVALID_ARGUMENT` (not a map, or index out of range).
/// Any thread.
#[no_mangle]
pub unsafe extern "C" fn cg_builtin_map_entry(
    which: i32,
    index: usize,
    smplx_joint: *mut *const c_char,
    bone: *mut *const c_char,
) -> cg_status {
    boundary("cg_builtin_map_entry", || {
        if smplx_joint.is_null() {
            return Err(null("smplx_joint"));
        }
        if bone.is_null() {
            return Err(null("bone"));
        }
        let which = read_map(which)?;
        let entries = &c_maps()[which as usize - 1];
        let (j, b) = entries
            .get(index)
            .ok_or_else(|| invalid(format_args!("index {index}: the map has {} entries", entries.len())))?;
        unsafe {
            smplx_joint.write(j.as_ptr());
            bone.write(b.as_ptr());
        }
        Ok(cg_status::CG_OK)
    })
}

unsafe fn skeleton_from_c(bones: *const cg_bone_desc, n_bones: usize) -> Result<HostSkeleton, Failure> {
    if bones.is_null() {
        return Err(null("bones"));
    }
    if n_bones == 0 || n_bones > CG_MAX_BONES {
        return Err(invalid(format_args!("n_bones must be 1..={CG_MAX_BONES}, got {n_bones}")));
    }
    let descs = unsafe { std::slice::from_raw_parts(bones, n_bones) };
    let mut out = Vec::with_capacity(n_bones);
    for (i, d) in descs.iter().enumerate() {
        let name = unsafe { name(d.name, &|| format!("bones[{i}].name"))? };
        let parent = match d.parent {
            -1 => None,
            p if p >= 0 => Some(p as usize),
            p => return Err(invalid(format_args!("bones[{i}].parent is {p}: a bone index or -1"))),
        };
        out.push(Bone {
            name: name.to_string(),
            parent,
            rest_translation: d.rest_translation,
            rest_rotation: d.rest_rotation,
        });
    }
    Ok(HostSkeleton { bones: out })
}

fn insert(retargeter: Retargeter, out: *mut *mut cg_retargeter) -> Result<cg_status, Failure> {
    let entry = Arc::new(RetargeterEntry { retargeter, poisoned: AtomicBool::new(false) });
    let handle = RETARGETERS
        .insert(entry)
        .ok_or_else(|| Failure::new(cg_status::CG_ERR_LIMIT, "too many retargeter handles"))?;
    unsafe { out.write(handle as *mut cg_retargeter) };
    Ok(cg_status::CG_OK)
}

fn rest_of(engine: *mut super::handle::cg_engine) -> Result<[[f32; 3]; crate::frame::CG_NUM_JOINTS], Failure> {
    lookup_engine(engine)?
        .engine
        .rest_joints()
        .ok_or_else(|| Failure::new(cg_status::CG_ERR_WRONG_STATE, "the engine has no model bundle (no rest skeleton)"))
}

/// Prepares retargeting onto the host's skeleton (`bones`, `n_bones`) with the host's own
/// map (`map`, `n_map`: which bone follows which SMPL-X joint; unmapped bones stay at
/// rest). The skeleton is in `engine`'s coordinate system and units; the retargeter serves
/// frames of any stream of an engine with the same bundle and coordinate system. On success
/// writes a handle to `*out` (destroy it with `cg_retargeter_destroy`). Errors:
/// `CG_ERR_NULL_POINTER`, `CG_ERR_INVALID_UTF8`, `CG_ERR_INVALID_ARGUMENT` (empty or
/// duplicate names, a parent out of range or a cycle, non-finite values, a non-unit rest
/// rotation, an unknown joint or bone in the map, a joint or bone mapped twice; the message
/// names it), `CG_ERR_INVALID_HANDLE`, `CG_ERR_WRONG_STATE` (an engine without a bundle).
/// Any thread.
#[no_mangle]
pub unsafe extern "C" fn cg_retargeter_create(
    engine: *mut super::handle::cg_engine,
    bones: *const cg_bone_desc,
    n_bones: usize,
    map: *const cg_bone_map_entry,
    n_map: usize,
    out: *mut *mut cg_retargeter,
) -> cg_status {
    boundary("cg_retargeter_create", || {
        if out.is_null() {
            return Err(null("out"));
        }
        let rest = rest_of(engine)?;
        let skeleton = unsafe { skeleton_from_c(bones, n_bones)? };
        if map.is_null() {
            return Err(null("map"));
        }
        if n_map > CG_MAX_BONES {
            return Err(invalid(format_args!("n_map must be at most {CG_MAX_BONES}, got {n_map}")));
        }
        let entries = unsafe { std::slice::from_raw_parts(map, n_map) };
        let mut pairs = Vec::with_capacity(n_map);
        for (i, e) in entries.iter().enumerate() {
            let j = unsafe { name(e.smplx_joint, &|| format!("map[{i}].smplx_joint"))? };
            let b = unsafe { name(e.bone, &|| format!("map[{i}].bone"))? };
            pairs.push((j, b));
        }
        insert(Retargeter::new(&rest, skeleton, &pairs)?, out)
    })
}

/// `cg_retargeter_create` with a ready map (`which`: a `cg_builtin_map`): name the bones as
/// the map does; entries whose bone the skeleton lacks are skipped (an avatar without an
/// upper chest, toes or some fingers), so a skeleton that has none of them is an error.
#[no_mangle]
pub unsafe extern "C" fn cg_retargeter_create_builtin(
    engine: *mut super::handle::cg_engine,
    bones: *const cg_bone_desc,
    n_bones: usize,
    which: i32,
    out: *mut *mut cg_retargeter,
) -> cg_status {
    boundary("cg_retargeter_create_builtin", || {
        if out.is_null() {
            return Err(null("out"));
        }
        let which = which_map(read_map(which)?);
        let rest = rest_of(engine)?;
        let skeleton = unsafe { skeleton_from_c(bones, n_bones)? };
        insert(Retargeter::with_builtin(&rest, skeleton, which)?, out)
    })
}

fn lookup(r: *mut cg_retargeter) -> Result<Arc<RetargeterEntry>, Failure> {
    if r.is_null() {
        return Err(null("retargeter"));
    }
    let entry = RETARGETERS.get(r as usize).ok_or_else(|| {
        Failure::new(cg_status::CG_ERR_INVALID_HANDLE, "retargeter is not a live cg_retargeter handle (destroyed?)")
    })?;
    if entry.poisoned.load(Ordering::SeqCst) {
        return Err(Failure::new(cg_status::CG_ERR_PANIC, "retargeter is poisoned by an earlier internal panic"));
    }
    Ok(entry)
}

/// Destroys a retargeter. NULL is accepted (`CG_OK`); a stale handle gives
/// `CG_ERR_INVALID_HANDLE`. Any thread.
#[no_mangle]
pub unsafe extern "C" fn cg_retargeter_destroy(retargeter: *mut cg_retargeter) -> cg_status {
    boundary("cg_retargeter_destroy", || {
        if retargeter.is_null() {
            return Ok(cg_status::CG_OK);
        }
        RETARGETERS.remove(retargeter as usize).ok_or_else(|| {
            Failure::new(cg_status::CG_ERR_INVALID_HANDLE, "retargeter is not a live cg_retargeter handle")
        })?;
        Ok(cg_status::CG_OK)
    })
}

/// Writes the number of bones (the length `cg_retarget_frame` fills) to `*count`.
#[no_mangle]
pub unsafe extern "C" fn cg_retargeter_bone_count(retargeter: *mut cg_retargeter, count: *mut usize) -> cg_status {
    boundary("cg_retargeter_bone_count", || {
        if count.is_null() {
            return Err(null("count"));
        }
        let entry = lookup(retargeter)?;
        unsafe { count.write(entry.retargeter.bones().len()) };
        Ok(cg_status::CG_OK)
    })
}

/// Poses the host's skeleton for one engine frame: `out[i]` for bone `i` of the skeleton
/// given at creation (`n_out` must be the bone count), local and world transforms; and,
/// when `object` is not NULL, the object in the world and in each hand bone's frame (attach
/// it to the hand whose `contact` is 1). No allocation. Errors: `CG_ERR_NULL_POINTER`,
/// `CG_ERR_INVALID_HANDLE`, `CG_ERR_INVALID_ARGUMENT` (wrong `n_out`; a frame with a NaN,
/// infinite or non-unit rotation or position: nothing is written). Any thread, also
/// concurrently on one retargeter.
#[no_mangle]
pub unsafe extern "C" fn cg_retarget_frame(
    retargeter: *mut cg_retargeter,
    frame: *const cg_frame,
    out: *mut cg_bone_pose,
    n_out: usize,
    object: *mut cg_retarget_object,
) -> cg_status {
    boundary("cg_retarget_frame", || {
        if frame.is_null() {
            return Err(null("frame"));
        }
        if out.is_null() {
            return Err(null("out"));
        }
        let entry = lookup(retargeter)?;
        let n = entry.retargeter.bones().len();
        if n_out != n {
            return Err(invalid(format_args!("n_out is {n_out}; the skeleton has {n} bones")));
        }
        let f = unsafe { &*frame };
        check_frame(f)?;
        let out = unsafe { std::slice::from_raw_parts_mut(out, n) };
        let object = if object.is_null() { None } else { Some(unsafe { &mut *object }) };
        entry.retargeter.apply(f, out, object);
        Ok(cg_status::CG_OK)
    })
}

fn check_frame(f: &cg_frame) -> Result<(), Failure> {
    let quats = [&f.root_rotation, &f.object_rotation]
        .into_iter()
        .chain(&f.body_rotations)
        .chain(&f.left_hand_rotations)
        .chain(&f.right_hand_rotations);
    for q in quats {
        let len = q.iter().map(|v| f64::from(*v).powi(2)).sum::<f64>().sqrt();
        if !(len - 1.0).abs().lt(&1e-3) {
            return Err(invalid(format_args!("frame has a rotation that is not a finite unit quaternion: {q:?}")));
        }
    }
    if !f.root_translation.iter().chain(&f.object_translation).all(|v| v.is_finite()) {
        return Err(invalid("frame has a non-finite position"));
    }
    Ok(())
}
