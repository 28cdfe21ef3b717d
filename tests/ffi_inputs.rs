//! Bad inputs through the C ABI: every one gives its documented status, never UB or a crash.
mod common;

use std::ffi::{c_char, CStr, CString};
use std::ptr::{null, null_mut};

use comgrasp::ffi::*;
use comgrasp::Frame;
use common::*;

fn st(e: &TestEngine, text: &[u8]) -> cg_status {
    let mut s = null_mut();
    let r = unsafe { cg_start_utf8(e.handle, text.as_ptr(), text.len(), null(), &mut s) };
    if r == cg_status::CG_OK {
        unsafe { cg_stream_destroy(s) };
    } else {
        assert!(s.is_null(), "out must not be written on failure");
    }
    r
}

#[test]
fn versions_and_status_strings() {
    assert_eq!(cg_abi_version(), CG_ABI_VERSION);
    assert_eq!(cg_frame_size(), std::mem::size_of::<Frame>());
    let v = unsafe { CStr::from_ptr(cg_version_string()) }.to_str().unwrap();
    assert_eq!(v, env!("CARGO_PKG_VERSION"));
    for code in -11..=3 {
        let s = unsafe { CStr::from_ptr(cg_status_string(code)) }.to_str().unwrap();
        assert!(s.starts_with("CG_"), "{code}: {s}");
    }
    for code in [i32::MIN, -12, 4, 1000, i32::MAX] {
        let s = unsafe { CStr::from_ptr(cg_status_string(code)) }.to_str().unwrap();
        assert_eq!(s, "unknown cg_status value");
    }
    assert_eq!(
        unsafe { CStr::from_ptr(cg_status_string(cg_status::CG_ERR_PANIC as i32)) }.to_str().unwrap().split(':').next(),
        Some("CG_ERR_PANIC")
    );
}

#[test]
fn null_pointers() {
    let e = TestEngine::new(64, 4);
    let text = c"hello";
    let mut s = null_mut();
    let mut f = Frame::default();
    unsafe {
        assert_eq!(cg_start(null_mut(), text.as_ptr(), null(), &mut s), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_start(e.handle, null(), null(), &mut s), cg_status::CG_ERR_NULL_POINTER);
        assert!(last_error().contains("text"), "{}", last_error());
        assert_eq!(cg_last_error_status(), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_start(e.handle, text.as_ptr(), null(), null_mut()), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_start_utf8(e.handle, null(), 0, null(), &mut s), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_poll_frame(null_mut(), &mut f), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_stream_wait(null_mut(), 1, &mut f), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_cancel(null_mut()), cg_status::CG_ERR_NULL_POINTER);
        let mut id = 0u64;
        assert_eq!(cg_stream_id(null_mut(), &mut id), cg_status::CG_ERR_NULL_POINTER);
        let mut out = null_mut();
        assert_eq!(cg_engine_create(null(), &mut out), cg_status::CG_ERR_NULL_POINTER);
        let cfg = cg_engine_config::default();
        assert_eq!(cg_engine_create(&cfg, null_mut()), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_engine_config_init(null_mut()), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_stream_config_init(null_mut()), cg_status::CG_ERR_NULL_POINTER);
        let mut n = 0u32;
        assert_eq!(cg_engine_stream_count(null_mut(), &mut n), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_engine_stream_count(e.handle, null_mut()), cg_status::CG_ERR_NULL_POINTER);

        // A live stream with NULL outputs.
        let s = e.start("chunks=1");
        assert_eq!(cg_poll_frame(s, null_mut()), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_stream_wait(s, 1, null_mut()), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_stream_id(s, null_mut()), cg_status::CG_ERR_NULL_POINTER);
        assert_eq!(cg_stream_destroy(s), cg_status::CG_OK);

        // Destroying NULL is a documented no-op.
        assert_eq!(cg_stream_destroy(null_mut()), cg_status::CG_OK);
        assert_eq!(cg_engine_destroy(null_mut()), cg_status::CG_OK);
    }
    e.destroy();
}

#[test]
fn text_validation() {
    let e = TestEngine::new(64, 4);
    assert_eq!(st(&e, b"a woman drinks from the mug"), cg_status::CG_OK);
    assert_eq!(st(&e, "une tasse de caf\u{e9}".as_bytes()), cg_status::CG_OK);
    assert_eq!(st(&e, b""), cg_status::CG_ERR_INVALID_ARGUMENT);
    assert_eq!(st(&e, b"  \t\n "), cg_status::CG_ERR_INVALID_ARGUMENT);
    assert_eq!(st(&e, b"\xff\xfe mug"), cg_status::CG_ERR_INVALID_UTF8);
    assert_eq!(st(&e, b"caf\xc3"), cg_status::CG_ERR_INVALID_UTF8, "truncated multi-byte sequence");
    assert_eq!(st(&e, b"mug\0cup"), cg_status::CG_ERR_INVALID_ARGUMENT, "embedded NUL");
    let max = vec![b'a'; CG_MAX_TEXT_BYTES as usize];
    assert_eq!(st(&e, &max), cg_status::CG_OK);
    let over = vec![b'a'; CG_MAX_TEXT_BYTES as usize + 1];
    assert_eq!(st(&e, &over), cg_status::CG_ERR_INVALID_ARGUMENT);
    assert!(last_error().contains("4096"), "{}", last_error());

    // The NUL-terminated entry point: same rules, and a long text is never scanned further
    // than the limit.
    let mut s = null_mut();
    unsafe {
        let ok = CString::new(vec![b'b'; CG_MAX_TEXT_BYTES as usize]).unwrap();
        assert_eq!(cg_start(e.handle, ok.as_ptr(), null(), &mut s), cg_status::CG_OK);
        assert_eq!(cg_stream_destroy(s), cg_status::CG_OK);
        let long = CString::new(vec![b'b'; 100_000]).unwrap();
        assert_eq!(cg_start(e.handle, long.as_ptr(), null(), &mut s), cg_status::CG_ERR_INVALID_ARGUMENT);
        assert_eq!(cg_start(e.handle, c"".as_ptr(), null(), &mut s), cg_status::CG_ERR_INVALID_ARGUMENT);
        assert_eq!(cg_start(e.handle, c"   ".as_ptr(), null(), &mut s), cg_status::CG_ERR_INVALID_ARGUMENT);
        let bad = [0xc3u8, 0x28, 0];
        assert_eq!(cg_start(e.handle, bad.as_ptr() as *const c_char, null(), &mut s), cg_status::CG_ERR_INVALID_UTF8);
    }
    assert_eq!(e.stream_count(), 0);
    e.destroy();
}

#[test]
fn stream_config_validation() {
    let e = TestEngine::new(64, 4);
    let mut s = null_mut();
    let mut cfg = cg_stream_config {
        struct_size: 0,
        use_defaults: 0,
        seed: 0,
        temperature: 0.0,
        top_k: 0,
        min_len: 0,
        max_len: 0,
        flags: 0,
        ..cg_stream_config::default()
    };
    unsafe {
        assert_eq!(cg_stream_config_init(&mut cfg), cg_status::CG_OK);
        assert_eq!(cfg.struct_size, 40, "the first version's entry point");
        assert_eq!(cg_stream_config_init_sized(&mut cfg, std::mem::size_of::<cg_stream_config>()), cg_status::CG_OK);
        assert_eq!(cfg.struct_size as usize, std::mem::size_of::<cg_stream_config>());
        assert_eq!(cfg.use_defaults, CG_USE_DEFAULT_ALL);
        assert_eq!(cg_start(e.handle, c"x".as_ptr(), &cfg, &mut s), cg_status::CG_OK);
        cg_stream_destroy(s);

        // An ignored field may hold anything; a used one is validated.
        cfg.temperature = -1.0;
        assert_eq!(cg_start(e.handle, c"x".as_ptr(), &cfg, &mut s), cg_status::CG_OK);
        cg_stream_destroy(s);
        cfg.use_defaults &= !CG_USE_DEFAULT_TEMPERATURE;
        assert_eq!(cg_start(e.handle, c"x".as_ptr(), &cfg, &mut s), cg_status::CG_ERR_INVALID_ARGUMENT);
        cfg.temperature = f64::NAN;
        assert_eq!(cg_start(e.handle, c"x".as_ptr(), &cfg, &mut s), cg_status::CG_ERR_INVALID_ARGUMENT);
        cfg.temperature = 0.0;
        cfg.use_defaults &= !(CG_USE_DEFAULT_MIN_LEN | CG_USE_DEFAULT_MAX_LEN);
        cfg.min_len = 5;
        cfg.max_len = 2;
        assert_eq!(cg_start(e.handle, c"x".as_ptr(), &cfg, &mut s), cg_status::CG_ERR_INVALID_ARGUMENT);
        cfg.max_len = 0;
        cfg.min_len = 0;
        assert_eq!(cg_start(e.handle, c"x".as_ptr(), &cfg, &mut s), cg_status::CG_ERR_INVALID_ARGUMENT);
        cfg.max_len = 8;
        assert_eq!(cg_start(e.handle, c"x".as_ptr(), &cfg, &mut s), cg_status::CG_OK);
        cg_stream_destroy(s);

        // Versioning: too small is rejected; a larger (newer) struct is read up to our size.
        cfg.struct_size = 4;
        assert_eq!(cg_start(e.handle, c"x".as_ptr(), &cfg, &mut s), cg_status::CG_ERR_INVALID_ARGUMENT);
        assert!(last_error().contains("struct_size"), "{}", last_error());
        #[repr(C)]
        struct Newer {
            base: cg_stream_config,
            extra: [u64; 4],
        }
        let mut newer = Newer { base: cg_stream_config::default(), extra: [u64::MAX; 4] };
        newer.base.struct_size = std::mem::size_of::<Newer>() as u32;
        assert_eq!(cg_start(e.handle, c"x".as_ptr(), &newer.base, &mut s), cg_status::CG_OK);
        cg_stream_destroy(s);
        cfg = cg_stream_config::default();
        cfg.flags = 1 << 7; // not a CG_STREAM_* flag
        assert_eq!(cg_start(e.handle, c"x".as_ptr(), &cfg, &mut s), cg_status::CG_ERR_INVALID_ARGUMENT);
    }
    e.destroy();
}

#[test]
fn engine_config_validation() {
    let mut cfg = cg_engine_config::default();
    let mut out: *mut cg_engine = null_mut();
    unsafe {
        assert_eq!(cg_engine_config_init_sized(&mut cfg, std::mem::size_of::<cg_engine_config>()), cg_status::CG_OK);
        assert_eq!(cfg.ring_capacity, 256);
        assert!(cfg.bundle_path.is_null());
        // NULL selects the embedded default bundle (tests/embedded_default.rs, bundle_env.rs);
        // without it the build has nothing to load.
        #[cfg(not(feature = "embedded-default"))]
        if std::env::var_os("COMGRASP_BUNDLE").is_none() {
            assert_eq!(cg_engine_create(&cfg, &mut out), cg_status::CG_ERR_BUNDLE);
            assert!(out.is_null());
        }
        cfg.bundle_path = c"/nonexistent/comgrasp-bundle".as_ptr();
        assert_eq!(cg_engine_create(&cfg, &mut out), cg_status::CG_ERR_BUNDLE);
        assert!(out.is_null());
        let bad_path = [0xffu8, 0];
        cfg.bundle_path = bad_path.as_ptr() as *const c_char;
        assert_eq!(cg_engine_create(&cfg, &mut out), cg_status::CG_ERR_INVALID_UTF8);
        cfg.bundle_path = c"/nonexistent".as_ptr();
        for (field, value) in
            [("ring_capacity", 0u32), ("ring_capacity", 1 << 20), ("max_streams", 0), ("enable_fk", 2)]
        {
            let mut c = cfg;
            match field {
                "ring_capacity" => c.ring_capacity = value,
                "max_streams" => c.max_streams = value,
                _ => c.enable_fk = value,
            }
            assert_eq!(cg_engine_create(&c, &mut out), cg_status::CG_ERR_INVALID_ARGUMENT, "{field}={value}");
        }
        let mut c = cfg;
        c.struct_size = 3;
        assert_eq!(cg_engine_create(&c, &mut out), cg_status::CG_ERR_INVALID_ARGUMENT);
        // An out-of-range coordinate system written as a plain integer by C.
        let mut c = cfg;
        std::ptr::addr_of_mut!(c.coordinate_system).cast::<u32>().write(7);
        let p: *const cg_engine_config = std::ptr::addr_of!(c);
        assert_eq!(cg_engine_create(p, &mut out), cg_status::CG_ERR_INVALID_ARGUMENT);
        assert!(out.is_null());
    }
}

#[test]
fn invalid_handles() {
    let e = TestEngine::new(64, 4);
    let mut f = Frame::default();
    let mut s = null_mut();
    unsafe {
        // A foreign pointer (real memory, not a handle) and garbage values.
        let foreign = Box::into_raw(Box::new([0u64; 64]));
        for bogus in [foreign as usize, 1, 0x9, 0x5, usize::MAX, 0xdead_beef_0000] {
            assert_eq!(cg_poll_frame(bogus as *mut cg_stream, &mut f), cg_status::CG_ERR_INVALID_HANDLE, "{bogus:#x}");
            assert_eq!(cg_cancel(bogus as *mut cg_stream), cg_status::CG_ERR_INVALID_HANDLE);
            assert_eq!(cg_stream_destroy(bogus as *mut cg_stream), cg_status::CG_ERR_INVALID_HANDLE);
            assert_eq!(
                cg_start(bogus as *mut cg_engine, c"x".as_ptr(), null(), &mut s),
                cg_status::CG_ERR_INVALID_HANDLE
            );
            assert_eq!(cg_engine_destroy(bogus as *mut cg_engine), cg_status::CG_ERR_INVALID_HANDLE);
        }
        drop(Box::from_raw(foreign));

        // Wrong type: an engine handle used as a stream and vice versa.
        let stream = e.start("chunks=1");
        assert_eq!(cg_poll_frame(e.handle as *mut cg_stream, &mut f), cg_status::CG_ERR_INVALID_HANDLE);
        assert_eq!(cg_stream_destroy(e.handle as *mut cg_stream), cg_status::CG_ERR_INVALID_HANDLE);
        assert_eq!(cg_start(stream as *mut cg_engine, c"x".as_ptr(), null(), &mut s), cg_status::CG_ERR_INVALID_HANDLE);
        assert_eq!(cg_engine_destroy(stream as *mut cg_engine), cg_status::CG_ERR_INVALID_HANDLE);

        // Double destroy and use after destroy.
        assert_eq!(cg_stream_destroy(stream), cg_status::CG_OK);
        assert_eq!(cg_stream_destroy(stream), cg_status::CG_ERR_INVALID_HANDLE);
        assert!(last_error().contains("already destroyed"), "{}", last_error());
        assert_eq!(cg_poll_frame(stream, &mut f), cg_status::CG_ERR_INVALID_HANDLE);
        assert_eq!(cg_stream_wait(stream, 5, &mut f), cg_status::CG_ERR_INVALID_HANDLE);
        assert_eq!(cg_cancel(stream), cg_status::CG_ERR_INVALID_HANDLE);
        let mut id = 0;
        assert_eq!(cg_stream_id(stream, &mut id), cg_status::CG_ERR_INVALID_HANDLE);

        // A new stream in the recycled slot gets a different handle; the old one stays dead.
        let again = e.start("chunks=1");
        assert_ne!(again, stream);
        assert_eq!(cg_poll_frame(stream, &mut f), cg_status::CG_ERR_INVALID_HANDLE);
        assert_eq!(cg_stream_destroy(again), cg_status::CG_OK);
    }
    let h = e.handle;
    e.destroy();
    unsafe {
        assert_eq!(cg_engine_destroy(h), cg_status::CG_ERR_INVALID_HANDLE);
        assert_eq!(cg_start(h, c"x".as_ptr(), null(), &mut s), cg_status::CG_ERR_INVALID_HANDLE);
        let mut n = 0;
        assert_eq!(cg_engine_stream_count(h, &mut n), cg_status::CG_ERR_INVALID_HANDLE);
    }
}

#[test]
fn last_error_buffer_convention() {
    let mut s = null_mut();
    unsafe {
        assert_eq!(cg_start(null_mut(), c"x".as_ptr(), null(), &mut s), cg_status::CG_ERR_NULL_POINTER);
        let msg = last_error();
        assert_eq!(msg, "engine is NULL");
        let need = cg_last_error_message(null_mut(), 0);
        assert_eq!(need, msg.len() + 1);
        let mut small = [0x55 as c_char; 4];
        assert_eq!(cg_last_error_message(small.as_mut_ptr(), small.len()), need);
        assert_eq!(CStr::from_ptr(small.as_ptr()).to_str().unwrap(), "eng");
        let mut big = [0x55 as c_char; 64];
        cg_last_error_message(big.as_mut_ptr(), big.len());
        assert_eq!(CStr::from_ptr(big.as_ptr()).to_str().unwrap(), msg);
        // Successful calls leave the message alone; other threads have their own.
        assert_eq!(cg_abi_version(), 1);
        assert_eq!(last_error(), msg);
        std::thread::spawn(|| assert_eq!(last_error(), "")).join().unwrap();
    }
}
