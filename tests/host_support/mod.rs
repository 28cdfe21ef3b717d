//! Shared by the native-host tests (`cmake_package`, `csharp_binding`, `python_binding`):
//! finding the freshly built library, requiring system tools, running programs with a time
//! limit, and the C compiler's layout of the ABI structs (`layout.c`).
//!
//! A missing tool FAILS a test (it never skips): CI installs them with
//! `scripts/setup_system.sh` (called by `scripts/test_all.sh`).
#![allow(dead_code)]

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

/// The repository root: the library crate's directory, the parent of the cli/ member's.
pub fn root() -> &'static Path {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    if dir.join("models").is_dir() {
        dir
    } else {
        dir.parent().expect("cli/ has a parent")
    }
}

/// The small random-weight bundle.
pub fn tiny() -> PathBuf {
    root().join("models/tiny")
}

/// This test binary's scratch folder under `target/tmp`.
pub fn scratch(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(name);
    std::fs::create_dir_all(&d).unwrap();
    d
}

pub fn shared_lib_name() -> &'static str {
    if cfg!(target_os = "macos") {
        "libcomgrasp.dylib"
    } else {
        "libcomgrasp.so"
    }
}

/// The folder holding the freshest `libcomgrasp` (shared and static). rustc writes every
/// crate type of the lib into `deps/` whenever `cargo test` compiles it, so the test
/// binary's own folder always has the current build; the copy in the profile folder only
/// exists after `cargo build` and may be stale, so it is only a fallback (as in
/// tests/c_example.rs).
pub fn lib_dir() -> PathBuf {
    let name = shared_lib_name();
    let exe = std::env::current_exe().expect("test binary path");
    let deps = exe.parent().expect("deps folder").to_path_buf();
    let candidates = [deps.clone(), deps.parent().expect("profile folder").to_path_buf()];
    candidates
        .iter()
        .find(|d| d.join(name).is_file() && d.join("libcomgrasp.a").is_file())
        .cloned()
        .unwrap_or_else(|| panic!("{name} + libcomgrasp.a not found in {candidates:?}; are crate-types cdylib and staticlib still in Cargo.toml?"))
}

/// Compiles `sources` with `$env_var` (else `compiler`) against `include/comgrasp.h` and the
/// freshly built shared library (linked by absolute path with an rpath, so no
/// `LD_LIBRARY_PATH`), warnings as errors, into `target/tmp/<out>`; returns the program.
pub fn compile(env_var: &str, compiler: &str, std: &str, sources: &[&str], out: &str, extra: &[&str]) -> PathBuf {
    let cc = std::env::var(env_var).unwrap_or_else(|_| compiler.into());
    require_tool(&cc, "--version");
    let dir = lib_dir();
    let exe = Path::new(env!("CARGO_TARGET_TMPDIR")).join(out);
    run_ok(
        Command::new(&cc)
            .current_dir(root())
            .args([std, "-g", "-Wall", "-Wextra", "-Wpedantic", "-Werror", "-Iinclude", "-Ibindings/cpp"])
            .args(sources)
            .arg("-o")
            .arg(&exe)
            .arg(format!("-L{}", dir.display()))
            .arg("-lcomgrasp")
            .arg(format!("-Wl,-rpath,{}", dir.display()))
            .args(extra),
        Duration::from_secs(300),
    );
    exe
}

/// `target/<profile>`, where build.rs (build/packaging.rs) writes comgrasp.pc and the CMake package.
pub fn profile_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test binary path");
    exe.parent().and_then(Path::parent).expect("profile folder").to_path_buf()
}

/// Fails (never skips) when `tool` cannot be run, naming the script that installs it.
pub fn require_tool(tool: &str, version_arg: &str) {
    let ok = Command::new(tool).arg(version_arg).stdout(Stdio::null()).stderr(Stdio::null()).status().is_ok();
    assert!(
        ok,
        "`{tool}` is not installed (or not on PATH); this test needs it. Install the system tools with \
         `bash scripts/setup_system.sh` (scripts/test_all.sh runs it)"
    );
}

/// Runs a command, killing it after `limit` so a hang fails the test instead of the CI job.
pub fn run(cmd: &mut Command, limit: Duration) -> Output {
    let mut child = cmd
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot run {cmd:?}: {e}"));
    // Drain both pipes on threads so a chatty child never blocks on a full pipe.
    let drain = |mut r: Box<dyn Read + Send>| {
        std::thread::spawn(move || {
            let mut v = Vec::new();
            let _ = r.read_to_end(&mut v);
            v
        })
    };
    let out = drain(Box::new(child.stdout.take().unwrap()));
    let err = drain(Box::new(child.stderr.take().unwrap()));
    let t0 = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().expect("wait") {
            break s;
        }
        if t0.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{cmd:?} did not finish within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    Output { status, stdout: out.join().unwrap(), stderr: err.join().unwrap() }
}

/// Runs a command that must succeed; returns its stdout. The failure message has both streams.
pub fn run_ok(cmd: &mut Command, limit: Duration) -> String {
    let o = run(cmd, limit);
    let (stdout, stderr) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert!(o.status.success(), "{cmd:?} failed ({}):\nstdout:\n{stdout}\nstderr:\n{stderr}", o.status);
    stdout.into_owned()
}

/// The C compiler's sizes and offsets of `cg_frame`, `cg_engine_config` and `cg_stream_config`
/// (`tests/host_support/layout.c` compiled with `$CC` or `cc` and run), as a file the binding
/// tests compare their declarations with. Built once per test binary.
pub fn c_layout() -> &'static Path {
    static FILE: OnceLock<PathBuf> = OnceLock::new();
    FILE.get_or_init(|| {
        let cc = std::env::var("CC").unwrap_or_else(|_| "cc".into());
        require_tool(&cc, "--version");
        let dir = scratch("host_layout");
        let exe = dir.join(format!("layout-{}", std::process::id()));
        run_ok(
            Command::new(&cc)
                .current_dir(root())
                .args(["-std=c11", "-Wall", "-Wextra", "-Werror", "-Iinclude", "tests/host_support/layout.c", "-o"])
                .arg(&exe),
            Duration::from_secs(120),
        );
        let text = run_ok(&mut Command::new(&exe), Duration::from_secs(30));
        let _ = std::fs::remove_file(&exe);
        assert!(text.contains("size cg_frame 1608"), "cg_frame is no longer 1608 bytes; update the bindings:\n{text}");
        let file = dir.join(format!("layout-{}.txt", std::process::id()));
        std::fs::write(&file, text).unwrap();
        file
    })
}

/// The `N passed, M failed` closing line of a binding's own test program: asserts M == 0
/// and N >= `at_least`.
pub fn check_closing_line(stdout: &str, at_least: u32) {
    let line = stdout
        .lines()
        .rev()
        .find(|l| l.contains(" passed, ") && l.ends_with(" failed"))
        .unwrap_or_else(|| panic!("no `N passed, M failed` line in:\n{stdout}"));
    let nums: Vec<u32> =
        line.split(|c: char| !c.is_ascii_digit()).filter(|s| !s.is_empty()).map(|s| s.parse().unwrap()).collect();
    assert!(nums.len() == 2 && nums[1] == 0 && nums[0] >= at_least, "{line}\n{stdout}");
}

/// The value after `key` on the first line of `stdout` that starts with it.
pub fn field<'a>(stdout: &'a str, key: &str) -> &'a str {
    stdout.lines().find_map(|l| l.strip_prefix(key)).unwrap_or_else(|| panic!("no {key:?} line in:\n{stdout}")).trim()
}
