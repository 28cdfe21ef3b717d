//! The Python binding (the package `comgrasp` in bindings/python, module `comgrasp_ctypes`)
//! against the real library: installs the package with the freshly built `libcomgrasp.so`
//! inside (`pip install --target`, the project's venv, no network), then runs
//! bindings/python/tests/test_comgrasp_ctypes.py against the *installed* package with the tiny
//! bundle, the C compiler's struct layout (tests/host_support/layout.c) to compare `CgFrame`
//! with, and cli/tests/bvh_check.py for `Engine.write_bvh`. Also checks, with the system
//! `python3` (standard library only), how the single-file module finds the library.
//!
//! python3 and the project's venv (`scripts/setup_python.sh`) must exist; a missing one
//! fails the test.
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
fn python_package_installs_and_passes_its_tests_against_the_library() {
    let lib = lib_dir().join(shared_lib_name());
    let venv_python = root().join(".venv/bin/python");
    assert!(venv_python.exists(), "{} is missing: run scripts/setup_python.sh", venv_python.display());
    let site = scratch("python_binding").join("site");
    let _ = std::fs::remove_dir_all(&site);
    // The package's build step copies the library named by COMGRASP_LIB into the wheel.
    run_ok(
        Command::new(&venv_python)
            .args(["-m", "pip", "install", "--quiet", "--no-build-isolation", "--no-index", "--no-deps", "--target"])
            .arg(&site)
            .arg(root().join("bindings/python"))
            .env("COMGRASP_LIB", &lib)
            .env("PYTHONDONTWRITEBYTECODE", "1"),
        Duration::from_secs(600),
    );
    assert!(site.join("comgrasp_ctypes").join(shared_lib_name()).is_file(), "the package carries no library");
    let stdout = run_ok(
        Command::new(&venv_python)
            .arg("-s")
            .arg(root().join("bindings/python/tests/test_comgrasp_ctypes.py"))
            .env("PYTHONPATH", &site)
            .env("PYTHONDONTWRITEBYTECODE", "1")
            .env_remove("COMGRASP_LIB")
            .env("COMGRASP_TEST_BUNDLE", tiny())
            .env("COMGRASP_C_LAYOUT", c_layout())
            .env("COMGRASP_BVH_CHECK", root().join("cli/tests/bvh_check.py")),
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
        "test_installed_package_carries_its_library",
        "test_write_bvh_from_any_coordinate_system",
    ] {
        assert!(stdout.lines().any(|l| l == format!("ok {t}")), "no `ok {t}` in:\n{stdout}");
    }
    check_closing_line(&stdout, 15);
}

#[test]
fn python_binding_finds_the_library() {
    // Next to the module: a copy of the module in a scratch folder with the library beside it.
    let dir = scratch("python_binding").join("module");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    // (the package's one file, copied as a plain module)
    std::fs::copy(root().join("bindings/python/comgrasp_ctypes/__init__.py"), dir.join("comgrasp_ctypes.py")).unwrap();
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
