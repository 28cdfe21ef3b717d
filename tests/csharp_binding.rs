//! The C# binding (the Unity package's plain C#, bindings/unity/Runtime: Comgrasp.cs and
//! HumanoidRig.cs) against the real library: compiles it with `mcs` (Mono's C# compiler)
//! together with bindings/unity/Tests~/Test.cs and runs the test program with `mono`,
//! `LD_LIBRARY_PATH` pointing at the freshly built `libcomgrasp.so` so
//! `[DllImport("comgrasp")]` loads it. The package's ComGraspAnimator.cs and the sample's script
//! (UnityEngine only) are compiled against a stub of the UnityEngine types they use. Test.cs checks the struct layouts
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

    // The package's runtime must compile alone (it is what a Unity project imports), warnings
    // as errors: as plain C#, and with Unity's define against the UnityEngine stub.
    let runtime =
        ["Comgrasp.cs", "HumanoidRig.cs", "ComGraspAnimator.cs"].map(|f| format!("bindings/unity/Runtime/{f}"));
    for (dll, unity) in [("Comgrasp.dll", false), ("ComgraspUnity.dll", true)] {
        let mut mcs = Command::new("mcs");
        mcs.current_dir(root())
            .args(["-unsafe", "-warnaserror+", "-target:library", "-nologo"])
            .arg(format!("-out:{}", dir.join(dll).display()))
            .args(&runtime);
        if unity {
            mcs.arg("-define:UNITY_5_3_OR_NEWER")
                .arg("tests/host_support/UnityEngineStub.cs")
                .arg("bindings/unity/Samples~/GraspDemo/GraspDemoButtons.cs");
        }
        run_ok(&mut mcs, Duration::from_secs(300));
    }

    let exe = dir.join("comgrasp_cs_test.exe");
    run_ok(
        Command::new("mcs")
            .current_dir(root())
            .args(["-unsafe", "-warnaserror+", "-debug", "-nologo"])
            .arg(format!("-out:{}", exe.display()))
            .args(&runtime)
            .arg("bindings/unity/Tests~/Test.cs"),
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
    for group in groups.iter().chain(&[
        "runtime_options",
        "shm_subscriber",
        "shm_errors",
        "retarget",
        "humanoid_rig",
        "bvh",
        "unity_heading",
    ]) {
        assert!(stdout.lines().any(|l| l == format!("ok {group}")), "no `ok {group}` in:\n{stdout}");
    }
    check_closing_line(&stdout, 17);
}
