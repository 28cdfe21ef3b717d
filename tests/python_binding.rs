//! The Python ctypes binding (bindings/python/comgrasp_ctypes.py) against the real library:
//! runs bindings/python/test_comgrasp_ctypes.py with the system `python3` (standard library
//! only), `COMGRASP_LIB` = the freshly built `libcomgrasp.so`, the tiny bundle, and the C
//! compiler's struct layout (tests/host_support/layout.c) to compare `CgFrame` with. Also
//! checks how the module finds the library when `COMGRASP_LIB` is not set.
//!
//! python3 must be installed (`scripts/setup_system.sh`); a missing one fails the test.
#![cfg(target_os = "linux")]

mod host_support;

use std::process::Command;
use std::time::Duration;

use host_support::*;

fn python() -> Command {
    require_tool("python3", "--version");
    let mut c = Command::new("python3");
    // Keep the source tree free of __pycache__; ignore the user's site and PYTHONPATH.
    c.env("PYTHONDONTWRITEBYTECODE", "1").env_remove("PYTHONPATH").arg("-s");
    c
}

#[test]
fn python_binding_passes_its_tests_against_the_library() {
    let lib = lib_dir().join(shared_lib_name());
    let stdout = run_ok(
        python()
            .arg(root().join("bindings/python/test_comgrasp_ctypes.py"))
            .env("COMGRASP_LIB", &lib)
            .env("COMGRASP_TEST_BUNDLE", tiny())
            .env("COMGRASP_C_LAYOUT", c_layout()),
        Duration::from_secs(600),
    );
    for t in [
        "test_layout_matches_c",
        "test_stream_to_end",
        "test_errors",
        "test_runtime_options_change_how_not_what",
        "test_cancel",
        "test_cancel_from_another_thread",
        "test_shm_subscriber_receives_the_polled_frames",
        "test_shm_errors",
        "test_retarget_onto_a_unity_named_skeleton",
    ] {
        assert!(stdout.lines().any(|l| l == format!("ok {t}")), "no `ok {t}` in:\n{stdout}");
    }
    check_closing_line(&stdout, 13);
}

#[test]
fn python_binding_finds_the_library() {
    // Next to the module: a copy of the module in a scratch folder with the library beside it.
    let dir = scratch("python_binding").join("module");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(root().join("bindings/python/comgrasp_ctypes.py"), dir.join("comgrasp_ctypes.py")).unwrap();
    let lib = lib_dir().join(shared_lib_name());
    std::os::unix::fs::symlink(&lib, dir.join(shared_lib_name())).unwrap();
    let code = "import comgrasp_ctypes as c; print(c.find_library()); print(c.version()); \
                e = c.Engine(r'''BUNDLE'''); s = e.start('a mug'); print(len(s.frames()), s.status.name)";
    let out = run_ok(
        python()
            .current_dir(&dir)
            .env_remove("COMGRASP_LIB")
            .arg("-c")
            .arg(code.replace("BUNDLE", tiny().to_str().unwrap())),
        Duration::from_secs(300),
    );
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(lines[0], dir.join(shared_lib_name()).to_str().unwrap(), "{out}");
    assert_eq!(lines[1], env!("CARGO_PKG_VERSION"), "{out}");
    assert!(lines[2].ends_with(" END") && lines[2] != "0 END", "{out}");

    // COMGRASP_LIB naming a missing file is an error that names it.
    let o = run(
        python()
            .current_dir(&dir)
            .env("COMGRASP_LIB", "/nonexistent/libcomgrasp.so")
            .args(["-c", "import comgrasp_ctypes as c; c.load()"]),
        Duration::from_secs(60),
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("FileNotFoundError") && err.contains("/nonexistent/libcomgrasp.so"),
        "{err}"
    );
}
