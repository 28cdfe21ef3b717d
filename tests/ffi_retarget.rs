//! Retargeting through the C ABI on real frames (models/tiny): the ready maps, a skeleton
//! identical to SMPL-X in a mirrored coordinate system (Unity), bad skeletons, maps and
//! frames, handle misuse; and that posing a frame allocates nothing.
mod alloc_counter;
mod bundle_support;

use std::ffi::{c_char, CStr, CString};
use std::ptr::{null, null_mut};

use alloc_counter::allocations_in;
use bundle_support::*;
use comgrasp::ffi::retarget::*;
use comgrasp::ffi::*;
use comgrasp::retarget::{cg_bone_pose, cg_retarget_object, SMPLX_JOINT_NAMES};
use comgrasp::skeleton::SMPLX_PARENTS;
use comgrasp::{CoordinateSystem, Frame};

fn last_error() -> String {
    unsafe { CStr::from_ptr(cg_last_error()) }.to_string_lossy().into_owned()
}

fn engine(coords: CoordinateSystem) -> *mut cg_engine {
    let path = CString::new(tiny_dir().to_str().unwrap()).unwrap();
    let mut cfg = cg_engine_config::default();
    unsafe { cg_engine_config_init_sized(&mut cfg, std::mem::size_of::<cg_engine_config>()) };
    cfg.bundle_path = path.as_ptr();
    cfg.enable_fk = 1;
    cfg.coordinate_system = coords;
    let mut e = null_mut();
    assert_eq!(unsafe { cg_engine_create(&cfg, &mut e) }, cg_status::CG_OK, "{}", last_error());
    e
}

fn frames(e: *mut cg_engine, text: &str) -> Vec<Frame> {
    let c = CString::new(text).unwrap();
    let mut s = null_mut();
    assert_eq!(unsafe { cg_start(e, c.as_ptr(), null(), &mut s) }, cg_status::CG_OK, "{}", last_error());
    let (mut out, mut f) = (Vec::new(), Frame::default());
    loop {
        match unsafe { cg_stream_wait(s, 5_000, &mut f) } {
            cg_status::CG_OK => out.push(f),
            cg_status::CG_PENDING => {}
            cg_status::CG_END => break,
            st => panic!("{st:?}: {}", last_error()),
        }
    }
    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    out
}

/// The engine's own skeleton as a host would describe it: SMPL-X names, rest offsets from
/// the engine's rest joints (in its coordinate system), identity rest rotations.
fn smplx_bones(rest: &[[f32; 3]; 55], names: &[CString]) -> Vec<cg_bone_desc> {
    (0..55)
        .map(|j| {
            let p = SMPLX_PARENTS[j];
            let t = if p < 0 { rest[j] } else { std::array::from_fn(|i| rest[j][i] - rest[p as usize][i]) };
            cg_bone_desc {
                name: names[j].as_ptr(),
                parent: p,
                rest_translation: t,
                rest_rotation: [0.0, 0.0, 0.0, 1.0],
            }
        })
        .collect()
}

fn rest_joints(coords: CoordinateSystem) -> [[f32; 3]; 55] {
    let cfg = comgrasp::EngineConfig {
        bundle_path: Some(tiny_dir()),
        coordinate_system: coords,
        ..comgrasp::EngineConfig::default()
    };
    comgrasp::Engine::new(cfg).unwrap().rest_joints().unwrap()
}

#[test]
fn ready_maps_are_listed_and_checked() {
    for which in [1, 2, 3] {
        let mut n = 0usize;
        assert_eq!(unsafe { cg_builtin_map_size(which, &mut n) }, cg_status::CG_OK);
        assert_eq!(n, 52);
        let (mut j, mut b): (*const c_char, *const c_char) = (null(), null());
        for i in 0..n {
            assert_eq!(unsafe { cg_builtin_map_entry(which, i, &mut j, &mut b) }, cg_status::CG_OK);
            let joint = unsafe { CStr::from_ptr(j) }.to_str().unwrap();
            assert!(SMPLX_JOINT_NAMES.contains(&joint), "{joint}");
            assert!(!unsafe { CStr::from_ptr(b) }.to_bytes().is_empty());
        }
        assert_eq!(unsafe { cg_builtin_map_entry(which, n, &mut j, &mut b) }, cg_status::CG_ERR_INVALID_ARGUMENT);
        assert!(last_error().contains("52 entries"), "{}", last_error());
    }
    let mut n = 0usize;
    assert_eq!(unsafe { cg_builtin_map_size(0, &mut n) }, cg_status::CG_ERR_INVALID_ARGUMENT);
    assert_eq!(unsafe { cg_builtin_map_size(1, null_mut()) }, cg_status::CG_ERR_NULL_POINTER);
    let mut j: *const c_char = null();
    assert_eq!(unsafe { cg_builtin_map_entry(4, 0, &mut j, &mut j) }, cg_status::CG_ERR_INVALID_ARGUMENT);
    assert_eq!(unsafe { cg_builtin_map_entry(1, 0, null_mut(), &mut j) }, cg_status::CG_ERR_NULL_POINTER);
}

#[test]
fn the_engines_own_skeleton_reproduces_its_frames_in_unity_coordinates() {
    let coords = CoordinateSystem::CG_COORDS_UNITY;
    let e = engine(coords);
    let rest = rest_joints(coords);
    let names: Vec<CString> = SMPLX_JOINT_NAMES.iter().map(|n| CString::new(*n).unwrap()).collect();
    let bones = smplx_bones(&rest, &names);
    let map: Vec<cg_bone_map_entry> =
        names.iter().map(|n| cg_bone_map_entry { smplx_joint: n.as_ptr(), bone: n.as_ptr() }).collect();
    let mut r = null_mut();
    let st = unsafe { cg_retargeter_create(e, bones.as_ptr(), bones.len(), map.as_ptr(), map.len(), &mut r) };
    assert_eq!(st, cg_status::CG_OK, "{}", last_error());
    let mut count = 0usize;
    assert_eq!(unsafe { cg_retargeter_bone_count(r, &mut count) }, cg_status::CG_OK);
    assert_eq!(count, 55);
    let fr = frames(e, "A woman drinks from the mug");
    assert!(!fr.is_empty());
    let mut out = vec![cg_bone_pose::default(); 55];
    let mut obj = cg_retarget_object::default();
    for f in &fr {
        let st = unsafe { cg_retarget_frame(r, f, out.as_mut_ptr(), out.len(), &mut obj) };
        assert_eq!(st, cg_status::CG_OK, "{}", last_error());
        for (j, (pose, want)) in out.iter().zip(&f.joint_positions).enumerate() {
            let d: f32 = (0..3).map(|i| (pose.world_position[i] - want[i]).powi(2)).sum::<f32>().sqrt();
            assert!(d < 1e-3, "frame {} joint {j}: {d} m", f.frame_index);
        }
        assert_eq!(obj.contact, f.contact);
        assert_eq!(obj.hand_bone, [20, 21]);
        let d: f32 = (0..3).map(|i| (obj.world_position[i] - f.object_translation[i]).powi(2)).sum::<f32>().sqrt();
        assert!(d < 1e-4);
    }
    // Per frame, nothing is allocated (a host poses its character every tick).
    let n = allocations_in(|| {
        for f in &fr {
            assert_eq!(unsafe { cg_retarget_frame(r, f, out.as_mut_ptr(), 55, &mut obj) }, cg_status::CG_OK);
        }
    });
    assert_eq!(n, 0, "cg_retarget_frame allocated");
    // Wrong length, NULLs, a NaN frame: errors, nothing written.
    let before = out.clone();
    assert_eq!(
        unsafe { cg_retarget_frame(r, &fr[0], out.as_mut_ptr(), 54, null_mut()) },
        cg_status::CG_ERR_INVALID_ARGUMENT
    );
    assert!(last_error().contains("55 bones"), "{}", last_error());
    let mut bad = fr[0];
    bad.body_rotations[3] = [f32::NAN, 0.0, 0.0, 1.0];
    assert_eq!(
        unsafe { cg_retarget_frame(r, &bad, out.as_mut_ptr(), 55, null_mut()) },
        cg_status::CG_ERR_INVALID_ARGUMENT
    );
    bad = fr[0];
    bad.root_translation[1] = f32::INFINITY;
    assert_eq!(
        unsafe { cg_retarget_frame(r, &bad, out.as_mut_ptr(), 55, null_mut()) },
        cg_status::CG_ERR_INVALID_ARGUMENT
    );
    assert_eq!(out, before);
    assert_eq!(
        unsafe { cg_retarget_frame(r, null(), out.as_mut_ptr(), 55, null_mut()) },
        cg_status::CG_ERR_NULL_POINTER
    );
    assert_eq!(unsafe { cg_retarget_frame(r, &fr[0], null_mut(), 55, null_mut()) }, cg_status::CG_ERR_NULL_POINTER);
    assert_eq!(unsafe { cg_retargeter_destroy(r) }, cg_status::CG_OK);
    assert_eq!(unsafe { cg_retargeter_destroy(r) }, cg_status::CG_ERR_INVALID_HANDLE);
    assert_eq!(
        unsafe { cg_retarget_frame(r, &fr[0], out.as_mut_ptr(), 55, null_mut()) },
        cg_status::CG_ERR_INVALID_HANDLE
    );
    assert_eq!(unsafe { cg_retargeter_destroy(null_mut()) }, cg_status::CG_OK);
    assert_eq!(unsafe { cg_engine_destroy(e) }, cg_status::CG_OK);
}

#[test]
fn bad_skeletons_and_maps_are_clear_errors() {
    let coords = CoordinateSystem::CG_COORDS_NATIVE;
    let e = engine(coords);
    let rest = rest_joints(coords);
    let names: Vec<CString> = SMPLX_JOINT_NAMES.iter().map(|n| CString::new(*n).unwrap()).collect();
    let good = smplx_bones(&rest, &names);
    let mut r = null_mut();
    let create = |bones: &[cg_bone_desc], r: &mut *mut cg_retargeter| unsafe {
        cg_retargeter_create_builtin(e, bones.as_ptr(), bones.len(), 1, r)
    };
    // A ready map on bones not named its way matches nothing.
    assert_eq!(create(&good, &mut r), cg_status::CG_ERR_INVALID_ARGUMENT);
    assert!(last_error().contains("names no bone"), "{}", last_error());
    let mut dup = good.clone();
    dup[3].name = names[0].as_ptr();
    let map = [cg_bone_map_entry { smplx_joint: names[0].as_ptr(), bone: names[0].as_ptr() }];
    let custom = |bones: &[cg_bone_desc], map: &[cg_bone_map_entry], r: &mut *mut cg_retargeter| unsafe {
        cg_retargeter_create(e, bones.as_ptr(), bones.len(), map.as_ptr(), map.len(), r)
    };
    assert_eq!(custom(&dup, &map, &mut r), cg_status::CG_ERR_INVALID_ARGUMENT);
    assert!(last_error().contains("both named \"pelvis\""), "{}", last_error());
    let mut cyc = good.clone();
    cyc[0].parent = 3;
    assert_eq!(custom(&cyc, &map, &mut r), cg_status::CG_ERR_INVALID_ARGUMENT);
    assert!(last_error().contains("cycle"), "{}", last_error());
    let mut far = good.clone();
    far[5].parent = 99;
    assert_eq!(custom(&far, &map, &mut r), cg_status::CG_ERR_INVALID_ARGUMENT);
    far[5].parent = -2;
    assert_eq!(custom(&far, &map, &mut r), cg_status::CG_ERR_INVALID_ARGUMENT);
    let mut scaled = good.clone();
    scaled[7].rest_rotation = [0.0, 0.0, 0.0, 1.5];
    assert_eq!(custom(&scaled, &map, &mut r), cg_status::CG_ERR_INVALID_ARGUMENT);
    assert!(last_error().contains("unit quaternion"), "{}", last_error());
    let mut unnamed = good.clone();
    unnamed[2].name = null();
    assert_eq!(custom(&unnamed, &map, &mut r), cg_status::CG_ERR_NULL_POINTER);
    assert!(last_error().contains("bones[2].name"), "{}", last_error());
    let bad_utf8 = [0xffu8, 0xfe, 0];
    let mut bad = good.clone();
    bad[1].name = bad_utf8.as_ptr().cast();
    assert_eq!(custom(&bad, &map, &mut r), cg_status::CG_ERR_INVALID_UTF8);
    let long = CString::new("x".repeat(300)).unwrap();
    bad = good.clone();
    bad[1].name = long.as_ptr();
    assert_eq!(custom(&bad, &map, &mut r), cg_status::CG_ERR_INVALID_ARGUMENT);
    let tail = CString::new("tail").unwrap();
    let unknown = [cg_bone_map_entry { smplx_joint: tail.as_ptr(), bone: names[0].as_ptr() }];
    assert_eq!(custom(&good, &unknown, &mut r), cg_status::CG_ERR_INVALID_ARGUMENT);
    assert!(last_error().contains("not an SMPL-X joint"), "{}", last_error());
    let nobone = [cg_bone_map_entry { smplx_joint: names[0].as_ptr(), bone: tail.as_ptr() }];
    assert_eq!(custom(&good, &nobone, &mut r), cg_status::CG_ERR_INVALID_ARGUMENT);
    assert!(last_error().contains("no bone \"tail\""), "{}", last_error());
    assert_eq!(custom(&[], &map, &mut r), cg_status::CG_ERR_INVALID_ARGUMENT);
    assert_eq!(unsafe { cg_retargeter_create(e, null(), 3, map.as_ptr(), 1, &mut r) }, cg_status::CG_ERR_NULL_POINTER);
    assert_eq!(
        unsafe { cg_retargeter_create(e, good.as_ptr(), 55, null(), 0, &mut r) },
        cg_status::CG_ERR_NULL_POINTER
    );
    assert_eq!(
        unsafe { cg_retargeter_create(null_mut(), good.as_ptr(), 55, map.as_ptr(), 1, &mut r) },
        cg_status::CG_ERR_NULL_POINTER
    );
    assert_eq!(
        unsafe { cg_retargeter_create(e, good.as_ptr(), 55, map.as_ptr(), 1, null_mut()) },
        cg_status::CG_ERR_NULL_POINTER
    );
    assert!(r.is_null(), "out is written only on success");
    assert_eq!(unsafe { cg_engine_destroy(e) }, cg_status::CG_OK);
}

#[test]
fn bvh_files_through_the_c_abi_and_their_errors() {
    let e = engine(CoordinateSystem::CG_COORDS_UNITY);
    let fs = frames(e, "A woman drinks from the mug");
    let dir = std::env::temp_dir().join(format!("comgrasp-ffi-bvh-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = |n: &str| CString::new(dir.join(n).to_str().unwrap()).unwrap();
    let (body, obj) = (path("m.bvh"), path("m.object.bvh"));
    let st = unsafe { cg_engine_write_bvh(e, fs.as_ptr(), fs.len(), body.as_ptr(), obj.as_ptr()) };
    assert_eq!(st, cg_status::CG_OK, "{}", last_error());
    let text = std::fs::read_to_string(dir.join("m.bvh")).unwrap();
    assert!(text.starts_with("HIERARCHY\nROOT pelvis\n") && text.contains(&format!("Frames: {}\n", fs.len())));
    assert!(std::fs::read_to_string(dir.join("m.object.bvh")).unwrap().starts_with("HIERARCHY\nROOT object\n"));
    // object_path NULL: the body only
    let only = path("only.bvh");
    assert_eq!(unsafe { cg_engine_write_bvh(e, fs.as_ptr(), fs.len(), only.as_ptr(), null()) }, cg_status::CG_OK);
    let cases: [(cg_status, &str, cg_status); 5] = [
        (unsafe { cg_engine_write_bvh(e, null(), 3, body.as_ptr(), null()) }, "frames", cg_status::CG_ERR_NULL_POINTER),
        (
            unsafe { cg_engine_write_bvh(e, fs.as_ptr(), fs.len(), null(), null()) },
            "body_path",
            cg_status::CG_ERR_NULL_POINTER,
        ),
        (
            unsafe { cg_engine_write_bvh(e, fs.as_ptr(), fs.len(), c"\xff".as_ptr(), null()) },
            "UTF-8",
            cg_status::CG_ERR_INVALID_UTF8,
        ),
        (
            unsafe { cg_engine_write_bvh(e, fs.as_ptr(), fs.len(), c"".as_ptr(), null()) },
            "empty",
            cg_status::CG_ERR_INVALID_ARGUMENT,
        ),
        (
            unsafe { cg_engine_write_bvh(0x7777 as *mut cg_engine, fs.as_ptr(), fs.len(), body.as_ptr(), null()) },
            "handle",
            cg_status::CG_ERR_INVALID_HANDLE,
        ),
    ];
    for (st, word, want) in cases {
        assert_eq!(st, want, "{word}: {}", last_error());
    }
    let mut bad = fs[..1].to_vec();
    bad[0].object_translation[1] = f32::INFINITY;
    let nan = path("nan.bvh");
    assert_eq!(
        unsafe { cg_engine_write_bvh(e, bad.as_ptr(), 1, nan.as_ptr(), null()) },
        cg_status::CG_ERR_INVALID_ARGUMENT
    );
    assert!(last_error().contains("non-finite") && !dir.join("nan.bvh").exists(), "{}", last_error());
    assert_eq!(unsafe { cg_engine_destroy(e) }, cg_status::CG_OK);
    let _ = std::fs::remove_dir_all(&dir);
}
