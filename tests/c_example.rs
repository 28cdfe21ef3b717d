//! The C ABI as a real C (and C++) host sees it: compiles `examples_c/stream.c` and
//! `bindings/cpp/example.cpp` with the system compilers against `include/comgrasp.h` and the
//! freshly built shared library, runs them on the tiny bundle, and runs the C example under
//! valgrind (no invalid accesses, no definite or indirect leaks).
//! Programs are built by `host_support::compile` (the current library, linked by absolute
//! path with an rpath).
#![cfg(unix)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;
use std::time::Duration;

mod host_support;
use host_support::{compile, field, run as run_cmd};

const PROMPT: &str = "A woman drinks from the mug.";

fn tiny() -> String {
    host_support::tiny().to_string_lossy().into_owned()
}

fn c_example() -> &'static Path {
    static EXE: OnceLock<PathBuf> = OnceLock::new();
    EXE.get_or_init(|| compile("CC", "cc", "-std=c11", &["examples_c/stream.c"], "c_example_stream", &[]))
}

/// Runs a program, killing it after `limit` so a hang fails the test instead of the CI job.
fn run(program: &Path, args: &[&str], limit: Duration) -> Output {
    run_cmd(Command::new(program).args(args), limit)
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

fn check_summary(stdout: &str) {
    let frames: u64 = field(stdout, "frames:").split_whitespace().next().unwrap().parse().unwrap();
    assert!(frames > 0 && frames.is_multiple_of(16), "frames: {frames}\n{stdout}");
    assert_eq!(field(stdout, "status:"), "CG_END", "{stdout}");
    assert_eq!(field(stdout, "last frame flagged:"), "yes", "{stdout}");
    let contacts: Vec<u64> = field(stdout, "contact frames:")
        .split(|c: char| !c.is_ascii_digit())
        .filter(|s| !s.is_empty())
        .map(|s| s.parse().unwrap())
        .collect();
    assert!(contacts.len() == 2 && contacts.iter().all(|&c| c <= frames), "{stdout}");
}

#[test]
fn c_example_streams_a_motion_to_the_end() {
    let o = run(c_example(), &[&tiny(), PROMPT], Duration::from_secs(300));
    let stdout = text(&o.stdout);
    assert!(o.status.success(), "exit {:?}\nstdout:\n{stdout}\nstderr:\n{}", o.status, text(&o.stderr));
    check_summary(&stdout);
    assert_eq!(field(&stdout, "prompt:"), PROMPT);
}

#[test]
fn c_example_reports_errors_with_status_and_message() {
    let o = run(c_example(), &["/nonexistent/bundle"], Duration::from_secs(60));
    let stderr = text(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("cg_engine_create failed: CG_ERR_BUNDLE") && stderr.contains("/nonexistent/bundle"),
        "{stderr}"
    );

    let o = run(c_example(), &[&tiny(), "   "], Duration::from_secs(60));
    let stderr = text(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("cg_start failed: CG_ERR_INVALID_ARGUMENT") && stderr.contains("whitespace"), "{stderr}");
}

#[test]
fn c_example_is_clean_under_valgrind() {
    if Command::new("valgrind").arg("--version").output().is_err() {
        eprintln!("SKIPPED c_example_is_clean_under_valgrind: valgrind is not installed (apt-get install valgrind)");
        return;
    }
    // Only real defects count: invalid reads/writes, uses of uninitialised values, and
    // definite or indirect leaks. Threads of the runtime (rayon's pool) legitimately stay
    // "still reachable" / "possibly lost" at exit.
    let o = run_cmd(
        Command::new("valgrind")
            .args(["--leak-check=full", "--errors-for-leak-kinds=definite,indirect", "--error-exitcode=99"])
            // The same reviewed suppressions as scripts/sanitize.sh (each says why it exists).
            .arg(format!("--suppressions={}/scripts/valgrind.supp", env!("CARGO_MANIFEST_DIR")))
            .arg(c_example())
            .args([tiny().as_str(), PROMPT]),
        Duration::from_secs(600),
    );
    let (stdout, stderr) = (text(&o.stdout), text(&o.stderr));
    assert!(o.status.success(), "valgrind exit {:?}\n{stderr}", o.status);
    check_summary(&stdout);
    assert!(stderr.contains("ERROR SUMMARY: 0 errors"), "{stderr}");
    let leaks_ok = stderr.contains("All heap blocks were freed")
        || (stderr.contains("definitely lost: 0 bytes") && stderr.contains("indirectly lost: 0 bytes"));
    assert!(leaks_ok, "{stderr}");
}

#[test]
fn cpp_wrapper_example_runs() {
    let exe = compile("CXX", "c++", "-std=c++17", &["bindings/cpp/example.cpp"], "cpp_wrapper_example", &["-pthread"]);
    let o = run(&exe, &[&tiny(), "The man lifts a small cube."], Duration::from_secs(300));
    let stdout = text(&o.stdout);
    assert!(o.status.success(), "exit {:?}\nstdout:\n{stdout}\nstderr:\n{}", o.status, text(&o.stderr));
    assert!(stdout.contains("last frame flagged: yes"), "{stdout}");
    assert!(stdout.contains("blank prompt rejected: cg_start: CG_ERR_INVALID_ARGUMENT"), "{stdout}");
    assert!(stdout.contains("retargeted 32 frames onto 55 bones (pelvis -> pelvis ...)"), "{stdout}");
    assert_eq!(stdout.lines().last(), Some("ok"), "{stdout}");
}
