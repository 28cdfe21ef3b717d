//! The real pipeline through the C ABI on the tiny bundle (models/tiny): text → tokens →
//! frames, checked against the PyTorch parity vectors (token count from the recorded
//! sequence, frame content from the recorded decode), the is_last policy on both ways a
//! sequence ends (End sampled, End forced by max_len), determinism and cancellation.
mod bundle_support;

use std::ffi::{CStr, CString};
use std::ptr::{null, null_mut};
use std::time::{Duration, Instant};

use bundle_support::*;
use comgrasp::ffi::*;
use comgrasp::Frame;

struct Eng(*mut cg_engine);
unsafe impl Send for Eng {}
unsafe impl Sync for Eng {}

fn last_error() -> String {
    unsafe { CStr::from_ptr(cg_last_error()) }.to_string_lossy().into_owned()
}

fn engine(enable_fk: bool) -> Eng {
    let path = CString::new(tiny_dir().to_str().unwrap()).unwrap();
    let mut cfg = cg_engine_config::default();
    unsafe { cg_engine_config_init_sized(&mut cfg, std::mem::size_of::<cg_engine_config>()) };
    cfg.bundle_path = path.as_ptr();
    cfg.enable_fk = enable_fk as u32;
    let mut e = null_mut();
    let st = unsafe { cg_engine_create(&cfg, &mut e) };
    assert_eq!(st, cg_status::CG_OK, "{}", last_error());
    Eng(e)
}

fn run(e: &Eng, text: &str, cfg: Option<&cg_stream_config>) -> (Vec<Frame>, cg_status) {
    let c = CString::new(text).unwrap();
    let mut s = null_mut();
    let st = unsafe { cg_start(e.0, c.as_ptr(), cfg.map_or(null(), |c| c as *const _), &mut s) };
    assert_eq!(st, cg_status::CG_OK, "{}", last_error());
    let mut id = 0;
    unsafe { cg_stream_id(s, &mut id) };
    let mut frames = Vec::new();
    let mut f = Frame::default();
    let t0 = Instant::now();
    let status = loop {
        match unsafe { cg_stream_wait(s, 1_000, &mut f) } {
            cg_status::CG_OK => {
                assert_eq!(f.stream_id, id);
                assert_eq!(f.frame_index, frames.len() as u64, "consecutive frame indices");
                assert!(frames.last().is_none_or(|p: &Frame| p.is_last == 0), "frame after is_last");
                frames.push(f);
            }
            cg_status::CG_PENDING => assert!(t0.elapsed() < Duration::from_secs(120), "no progress"),
            other => break other,
        }
    };
    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    (frames, status)
}

fn check_is_last(frames: &[Frame]) {
    let n = frames.len();
    for (i, f) in frames.iter().enumerate() {
        assert_eq!(f.is_last == 1, i + 1 == n, "is_last on frame {i} of {n}");
    }
}

#[test]
fn default_sampling_matches_the_recorded_sequence() {
    let dir = tiny_dir();
    let index = parity_index(&dir);
    let e = engine(true);
    for (case, expected_len) in [(0usize, 7usize), (1, 17)] {
        let step = &index["step"][case];
        let prompt = step["prompt"].as_str().unwrap();
        assert_eq!(step["length"].as_u64().unwrap() as usize, expected_len);
        // Defaults (NULL config) are the bundle's: seed 7, the recorded sampling params.
        let (frames, status) = run(&e, prompt, None);
        assert_eq!(status, cg_status::CG_END, "{}", last_error());
        assert_eq!(frames.len(), 16 * expected_len, "{prompt:?}: tokens x 16 frames");
        check_is_last(&frames);
        assert!(frames.iter().all(|f| f.has_joint_positions == 1));
        assert!((frames[30].time_s - 1.0).abs() < 1e-9, "30 fps");
    }
    // Frame content of case 0 against PyTorch's de-normalized offline decode
    // (native coordinates: positions unchanged).
    let (shape, want) = load_f32(&dir, "parity/decode/case0_frames_denormalized.npy");
    assert_eq!(shape, vec![112, 335]);
    // The model's raw output: the contact-consistency stage (on by default) moves the object.
    let mut raw = cg_stream_config::default();
    unsafe { cg_stream_config_init(&mut raw) };
    raw.flags = CG_STREAM_RAW_OUTPUT;
    let (frames, _) = run(&e, index["step"][0]["prompt"].as_str().unwrap(), Some(&raw));
    let mut worst = 0f64;
    for (i, f) in frames.iter().enumerate() {
        let row = &want[i * 335..(i + 1) * 335];
        for (got, at) in [(f.root_translation, 6), (f.object_translation, 15), (f.object_centre, 18)] {
            for a in 0..3 {
                worst = worst.max((got[a] as f64 - row[at + a] as f64).abs());
            }
        }
        for (h, ch) in [(0, 240), (1, 334)] {
            worst = worst.max((f.contact_probability[h] as f64 - row[ch].clamp(0.0, 1.0) as f64).abs());
        }
    }
    eprintln!("case 0 frames vs PyTorch: max abs diff {worst:.2e}");
    assert!(worst < 1e-3, "frames differ from PyTorch by {worst}");
    unsafe { cg_engine_destroy(e.0) };
}

#[test]
fn forced_end_greedy_and_max_len() {
    let e = engine(false);
    let prompt = "A woman drinks from the mug.";
    let mut cfg = cg_stream_config::default();
    unsafe { cg_stream_config_init(&mut cfg) };
    cfg.temperature = 0.0;
    cfg.use_defaults &= !CG_USE_DEFAULT_TEMPERATURE;
    // Greedy never samples End for this prompt (recorded: 18 = max_len codes): End forced.
    let (frames, status) = run(&e, prompt, Some(&cfg));
    assert_eq!(status, cg_status::CG_END);
    assert_eq!(frames.len(), 18 * 16);
    check_is_last(&frames);
    assert!(frames.iter().all(|f| f.has_joint_positions == 0));
    // A shorter max_len cuts it; the same prefix of frames (greedy is deterministic).
    cfg.max_len = 5;
    cfg.min_len = 0;
    cfg.use_defaults &= !(CG_USE_DEFAULT_MAX_LEN | CG_USE_DEFAULT_MIN_LEN);
    let (short, status) = run(&e, prompt, Some(&cfg));
    assert_eq!(status, cg_status::CG_END);
    assert_eq!(short.len(), 5 * 16);
    check_is_last(&short);
    for (a, b) in short.iter().zip(&frames) {
        assert_eq!(a.root_translation, b.root_translation);
        assert_eq!(a.body_rotations, b.body_rotations);
    }
    // max_len beyond the bundle's L_max is rejected at start.
    cfg.max_len = 1000;
    let mut s = null_mut();
    let st = unsafe { cg_start(e.0, c"x".as_ptr(), &cfg, &mut s) };
    assert_eq!(st, cg_status::CG_ERR_INVALID_ARGUMENT, "{}", last_error());
    unsafe { cg_engine_destroy(e.0) };
}

#[test]
fn concurrent_streams_are_deterministic_and_cancellable() {
    let e = std::sync::Arc::new(engine(true));
    let mut cfg = cg_stream_config { seed: 1234, ..Default::default() };
    cfg.use_defaults &= !CG_USE_DEFAULT_SEED;
    let runs: Vec<_> = (0..4)
        .map(|_| {
            let e = std::sync::Arc::clone(&e);
            std::thread::spawn(move || run(&e, "The man lifts a small cube.", Some(&cfg)).0)
        })
        .collect();
    let results: Vec<Vec<Frame>> = runs.into_iter().map(|t| t.join().unwrap()).collect();
    for r in &results[1..] {
        assert_eq!(r.len(), results[0].len());
        for (a, b) in r.iter().zip(&results[0]) {
            assert_eq!(a.joint_positions, b.joint_positions, "same seed, same motion");
        }
    }
    // Cancel a real stream right after its first frame.
    let mut s = null_mut();
    assert_eq!(unsafe { cg_start(e.0, c"A woman drinks from the mug.".as_ptr(), null(), &mut s) }, cg_status::CG_OK);
    let mut f = Frame::default();
    assert_eq!(unsafe { cg_stream_wait(s, 60_000, &mut f) }, cg_status::CG_OK);
    assert_eq!(unsafe { cg_cancel(s) }, cg_status::CG_OK);
    assert_eq!(unsafe { cg_poll_frame(s, &mut f) }, cg_status::CG_CANCELLED);
    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
    // Destroying the engine while a stream runs.
    assert_eq!(unsafe { cg_start(e.0, c"A woman drinks from the mug.".as_ptr(), null(), &mut s) }, cg_status::CG_OK);
    assert_eq!(unsafe { cg_engine_destroy(e.0) }, cg_status::CG_OK);
    let st = unsafe { cg_stream_wait(s, 60_000, &mut f) };
    assert!(st == cg_status::CG_CANCELLED || st == cg_status::CG_OK || st == cg_status::CG_END, "{st:?}");
    assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
}

#[test]
fn bad_bundle_path() {
    let mut cfg = cg_engine_config::default();
    let missing = c"/nonexistent/bundle";
    cfg.bundle_path = missing.as_ptr();
    let mut e = null_mut();
    assert_eq!(unsafe { cg_engine_create(&cfg, &mut e) }, cg_status::CG_ERR_BUNDLE);
    assert!(e.is_null());
    assert!(last_error().contains("/nonexistent/bundle"), "{}", last_error());
}

#[test]
fn stream_info_names_the_catalogue_object() {
    let e = engine(false);
    // (prompt, catalogue name, named): the tiny catalogue is mug, cubesmall, waterbottle.
    for (prompt, name, named) in [
        ("Lift the small cube", "cubesmall", 1),
        ("drink from the WATER BOTTLE", "waterbottle", 1),
        ("Hebe die Tasse", "mug", 0), // names nothing: the first object stands in
    ] {
        let c = CString::new(prompt).unwrap();
        let mut s = null_mut();
        assert_eq!(unsafe { cg_start(e.0, c.as_ptr(), null(), &mut s) }, cg_status::CG_OK);
        let mut info = cg_stream_info { stream_id: 0, object_index: 99, object_named: 9, object_name: [1; 64] };
        assert_eq!(unsafe { cg_stream_get_info(s, &mut info) }, cg_status::CG_OK, "{}", last_error());
        let mut id = 0;
        unsafe { cg_stream_id(s, &mut id) };
        let got = unsafe { std::ffi::CStr::from_ptr(info.object_name.as_ptr()) }.to_str().unwrap();
        assert_eq!((info.stream_id, got, info.object_named), (id, name, named), "{prompt:?}");
        let index = ["mug", "cubesmall", "waterbottle"].iter().position(|n| *n == name).unwrap();
        assert_eq!(info.object_index as usize, index);
        assert!(info.object_name[got.len()..].iter().all(|&b| b == 0), "NUL-padded");
        assert_eq!(unsafe { cg_stream_get_info(s, null_mut()) }, cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(unsafe { cg_stream_destroy(s) }, cg_status::CG_OK);
        assert_eq!(unsafe { cg_stream_get_info(s, &mut info) }, cg_status::CG_ERR_INVALID_HANDLE);
    }
    assert_eq!(unsafe { cg_stream_get_info(null_mut(), null_mut()) }, cg_status::CG_ERR_NULL_POINTER);
    unsafe { cg_engine_destroy(e.0) };
}
