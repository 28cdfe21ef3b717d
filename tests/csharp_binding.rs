//! The C# binding (bindings/csharp/Comgrasp.cs, the one for Unity) against the real library:
//! compiles it with `mcs` (Mono's C# compiler) together with bindings/csharp/Test.cs and runs
//! the test program with `mono`, `LD_LIBRARY_PATH` pointing at the freshly built
//! `libcomgrasp.so` so `[DllImport("comgrasp")]` loads it. Test.cs checks the struct layouts
//! against the C compiler's (tests/host_support/layout.c), streams motions of the tiny bundle
//! to the end (frame indices, stream ids, is_last, determinism, no allocation while polling),
//! error statuses and messages, thread-local errors, cancel (also from another thread) and
//! engine disposal.
//!
//! mcs and mono must be installed (Debian mono-mcs, mono-runtime: `scripts/setup_system.sh`);
//! a missing one fails the test.
#![cfg(target_os = "linux")]

mod host_support;

use std::process::Command;
use std::time::Duration;

use host_support::*;

#[test]
fn csharp_binding_passes_its_tests_against_the_library() {
    require_tool("mcs", "--version");
    require_tool("mono", "--version");
    let layout = c_layout();
    let dir = scratch("csharp_binding");

    // The binding alone must compile (it is what a Unity project copies), warnings as errors.
    let dll = dir.join("Comgrasp.dll");
    run_ok(
        Command::new("mcs")
            .current_dir(root())
            .args(["-unsafe", "-warnaserror+", "-target:library", "-nologo"])
            .arg(format!("-out:{}", dll.display()))
            .arg("bindings/csharp/Comgrasp.cs"),
        Duration::from_secs(300),
    );

    let exe = dir.join("comgrasp_cs_test.exe");
    run_ok(
        Command::new("mcs")
            .current_dir(root())
            .args(["-unsafe", "-warnaserror+", "-debug", "-nologo"])
            .arg(format!("-out:{}", exe.display()))
            .args(["bindings/csharp/Comgrasp.cs", "bindings/csharp/Test.cs"]),
        Duration::from_secs(300),
    );

    let stdout = run_ok(
        Command::new("mono")
            .arg("--debug")
            .arg(&exe)
            .arg(tiny())
            .arg(layout)
            .env("LD_LIBRARY_PATH", lib_dir())
            .env("MONO_PATH", &dir),
        Duration::from_secs(600),
    );
    let groups =
        ["layout", "stream_to_end", "polling_allocates_nothing", "errors", "cancel", "cancel_from_another_thread"];
    for group in groups.iter().chain(&["runtime_options", "shm_subscriber", "shm_errors", "retarget"]) {
        assert!(stdout.lines().any(|l| l == format!("ok {group}")), "no `ok {group}` in:\n{stdout}");
    }
    check_closing_line(&stdout, 14);
}
